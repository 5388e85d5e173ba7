"""
The base of the diagnosis report's records: frozen dataclasses whose ``as_dict()`` is JSON.

A record's fields are the keys of its part of the document, in the document's order. Fields
made by

- ``optional()`` are left out while None (keys only some reports carry);
- ``keyed()`` (or ``optional(key=)``) are written under a key that is no Python name (``from``);
- ``inline()`` hold a record whose keys stand in the parent's own (with a suffix);
- ``apart()`` are placed by the record's own ``as_dict``.

Values are kept as computed (Python or NumPy scalars, lists): ``as_dict()`` only turns records
into dicts and tuples into lists.
"""

from __future__ import annotations

from dataclasses import field, fields
from typing import Any, Optional


def optional(key: Optional[str] = None) -> Any:
    """
    Return a field for a key that only some documents carry (None: left out).

    Parameters
    ----------
    key : str, optional
        The document's key when it is not the field's name.

    """
    metadata = {'optional': True}
    if key is not None:
        metadata['key'] = key
    return field(default=None, metadata=metadata)


def keyed(key: str) -> Any:
    """Return a field written under ``key`` (a document key that is no Python name)."""
    return field(metadata={'key': key})


def inline(suffix: str = '') -> Any:
    """Return a field of a record whose keys (each with ``suffix``) stand in the parent's."""
    return field(metadata={'inline': suffix})


def apart() -> Any:
    """Return a field (default None) that the record's own ``as_dict`` places, not the base's."""
    return field(default=None, metadata={'apart': True})


class Record:
    """Base of the report's records: ``as_dict()`` gives the fields as keys, in their order."""

    def as_dict(self) -> dict:
        """Return the record as the JSON document's dict (plain types, keys in order)."""
        doc = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.metadata.get('apart') or (value is None and f.metadata.get('optional')):
                continue
            if 'inline' in f.metadata:
                suffix = f.metadata['inline']
                doc.update((k + suffix, v) for k, v in value.as_dict().items())
                continue
            doc[f.metadata.get('key', f.name)] = plain(value)
        return doc


def plain(value: Any) -> Any:
    """Return the JSON form of a value: records as dicts and tuples as lists, at any depth."""
    if isinstance(value, Record):
        return value.as_dict()
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    return value
