"""The data sketch's sorted unique hashes: the same as numpy's, by a sort."""

from coreg_ros.core import provenance
from coreg_ros.core.types import PoseStream
import numpy as np
import pytest


@pytest.mark.parametrize('n', [0, 1, 2, 7, 1000, 200_000])
@pytest.mark.parametrize('high', [3, 2**63])
def test_unique_is_numpys(n, high):
    rng = np.random.default_rng(n + high % 97)
    h = rng.integers(0, high, n, dtype=np.int64).view(np.uint64)
    got, want = provenance._unique(h), np.unique(h)
    assert got.dtype == want.dtype and np.array_equal(got, want)


def test_sketch_counts_repeated_samples_once():
    rng = np.random.default_rng(3)
    stamps = np.arange(5000, dtype=np.int64) * 1_000_000
    pos = rng.normal(size=(5000, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (5000, 1))
    once = PoseStream(stamps, pos, q)
    twice = PoseStream(np.concatenate([stamps, stamps]), np.vstack([pos, pos]), np.vstack([q, q]))
    a, b = provenance.data_sketch([once]), provenance.data_sketch([twice])
    assert a == b and a['samples'] == 5000 and len(a['hashes']) == provenance.SKETCH_SIZE
    assert a['hashes'] == sorted(a['hashes'])
