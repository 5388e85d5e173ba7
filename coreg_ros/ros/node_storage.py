"""
What coreg_node keeps on disk: the stored result, the sample journal, the samples on shutdown.

``NodeStorage`` is a part of ``coreg_ros.ros.node.CoregNode`` (a mixin: it uses the node's
buffers, configuration and logger). The result is stored atomically in ``storage_dir`` under a
name of the node and its configuration and republished at start-up only by a node of that
configuration; the accepted samples are journalled to rosbag2 chunks every ``FLUSH_PERIOD`` s
(``coreg_ros.ros.node``); a failing ``storage_dir`` sends the samples to a named temporary
folder and /diagnostics to ERROR.
"""

from __future__ import annotations

from pathlib import Path
import sys
import tempfile
from typing import Optional

from coreg_ros.core.errors import BagError, CoregError
from coreg_ros.ros import persistence


def os_reason(error: BaseException) -> str:
    """
    Return an OSError as 'strerror: file' (other errors as their text).

    Parameters
    ----------
    error : BaseException
        The failure to describe in one line.

    """
    if isinstance(error, OSError) and error.strerror:
        return f'{error.strerror}: {error.filename}' if error.filename else error.strerror
    return str(error) or type(error).__name__


class NodeStorage:
    """The stored result, the sample journal and the sample bags of ``CoregNode``."""

    def _storage_failed(self, what: str, error: BaseException) -> str:
        """Record that ``storage_dir`` failed (diagnostics ERROR); return the one line."""
        self._storage_error = (f'cannot {what} in storage_dir {self.config.storage_dir} '
                               f'({os_reason(error)}); fix storage_dir (a directory on a '
                               f'mounted disk with free space) and restart')
        self._warn_throttled(('storage', what), self._storage_error, level='error')
        return self._storage_error

    def fallback_dir(self) -> str:
        """Return a named temporary folder for what storage_dir cannot take (made once)."""
        if self._fallback_dir is None:
            self._fallback_dir = tempfile.mkdtemp(prefix=f'{self.get_name()}_samples_')
            self.get_logger().error(f'storage_dir failed: samples go to {self._fallback_dir}')
        return self._fallback_dir

    def _describe_config(self) -> str:
        return persistence.describe_config({'settings': self.config.settings.as_dict(),
                                            'frames': self.config.frames})

    def _republish_stored(self) -> None:
        """Republish the stored result of this node and configuration, and only that."""
        storage, log = self.config.storage_dir, self.get_logger()
        settings, frames = self.config.settings.as_dict(), self.config.frames
        try:
            stored = persistence.load_result(storage, self.result_name)
        except CoregError as e:
            log.error(str(e))
            stored = None
        for path in persistence.other_results(storage, self.get_name(), self.config_key):
            try:
                other = persistence.load_result(storage, path.name)
            except CoregError as e:
                log.warning(f'{e} (not republished)')
                continue
            if other is None:
                continue
            if (stored is None and path.name == persistence.RESULT_FILE
                    and persistence.matches_config(other[0], settings, frames)):
                stored = other  # an older version's result.yaml of this very configuration
                continue
            log.info(f'not republishing {path}: it was calibrated for '
                     f'{persistence.describe_config(other[0])}; this node is configured for '
                     f'{self._describe_config()}')
        if stored is None:
            return
        doc, base_to_base, tool_to_marker = stored
        stamp_ns = persistence.stamp_ns_of(doc)
        self._publish_result(base_to_base, tool_to_marker, stamp_ns)
        self.uncertainty.set_stored(doc, base_to_base, tool_to_marker)
        self.live.set_stored(doc, base_to_base, tool_to_marker)
        r = doc['result']
        dof = r.get('dof') or 0
        self._last = {'n_pairs': r.get('n_pairs'), 'success': r.get('success'),
                      'chi2_dof': (r['chi2'] / dof) if dof and r.get('chi2') is not None
                      else float('nan'),
                      'p_value': r.get('p_value'), 'seconds': None,
                      'pairing': f'stored result of {doc.get("saved_at", "?")}'}
        log.info(f'republished the stored result of {doc.get("saved_at", "?")} '
                 f'({r.get("n_pairs")} pairs, {self._describe_config()}), stamped with its '
                 f'calibration time')

    def _accepted_total(self) -> int:
        return sum(b.accepted for b in self.buffers.values())

    def save_samples(self, report=None) -> Optional[str]:
        """
        Write the held samples to a new bag in storage_dir; None if there are none.

        If storage_dir cannot be written, the bag goes to a named temporary folder instead
        and ``_last_save_error`` says why (diagnostics go ERROR). ``report`` (a callable
        taking one line) replaces the node logger, which cannot publish to /rosout any more
        once the context is shut down.
        """
        self._last_save_error = None
        with self._io_lock:
            accepted = self._accepted_total()
            streams = self.snapshot()
            if not any(len(s) for s in streams.values()):
                return None
            try:
                path = persistence.save_samples(self.config.storage_dir, streams)
            except (OSError, BagError) as e:
                self._last_save_error = self._storage_failed('save the samples', e)
                path = persistence.save_samples(self.fallback_dir(), streams)
            self._saved_accepted = accepted
        line = f'saved {sum(len(s) for s in streams.values())} samples to {path}'
        (report or self.get_logger().info)(line)
        return str(path)

    _last_save_error: Optional[str] = None

    def save_on_shutdown(self) -> bool:
        """
        Save the samples received since the last save, if any (called on shutdown).

        Returns False if they could not be saved anywhere (the journal is then kept).
        """
        def report(line):
            print(f'coreg_node: {line}', file=sys.stderr)

        saved = True
        if self._accepted_total() != self._saved_accepted:
            try:
                self.save_samples(report=report)
                if self._last_save_error:
                    report(self._last_save_error)
            except Exception as e:  # shutting down: report, do not raise over the real exit
                report(f'could not save the samples on shutdown: {os_reason(e)}')
                saved = False
        if saved and self.journal is not None:
            self.journal.remove()  # a clean end: the samples are in the bag
        elif self.journal is not None:
            report(f'the samples are still in the journal {self.journal.folder}')
        return saved

    # --- journal ----------------------------------------------------------------------------

    def _start_journal(self) -> None:
        """Open this session's journal; resume or report a journal a killed session left."""
        storage, name, key = self.config.storage_dir, self.get_name(), self.config_key
        left = persistence.left_over_journals(storage, name, key)
        if self.journal is not None:
            left = [p for p in left if p != self.journal.folder]
        if left and self.config.resume_samples and self._accepted_total() == 0:
            try:
                self._resume(left[-1])
                left = left[:-1]
            except Exception as e:
                self.get_logger().error(f'cannot resume the journal {left[-1]}: '
                                        f'{os_reason(e)}; it is kept, starting afresh')
        self._left_over = left
        for path in left:
            self.get_logger().warning(
                f'an interrupted session (the node was killed) left samples in {path}; '
                f'restart with resume_samples:=true to continue from them (the newest)')
        if self.journal is None:
            try:
                self.journal = persistence.SampleJournal(
                    persistence.new_journal_path(storage, name, key))
            except (OSError, BagError) as e:
                self._storage_failed('write the sample journal', e)
                self.journal = persistence.SampleJournal(
                    persistence.new_journal_path(self.fallback_dir(), name, key))

    def _resume(self, folder: Path) -> None:
        """Load a left-over journal into the buffers and continue writing it."""
        streams = persistence.read_journal(folder, self.topics)
        n = 0
        for topic, s in streams.items():
            b = self.buffers[topic]
            before = b.accepted
            b.push_many(s.stamps, s.receive_stamps, s.position, s.quat_wxyz, s.frame_id)
            n += b.accepted - before
            self.gaps[topic].update(s.stamps)
        # This session's journal starts with them, in one bag; then the old one goes.
        self.journal = persistence.SampleJournal(persistence.new_journal_path(
            self.config.storage_dir, self.get_name(), self.config_key))
        self.journal.append({t: b.since(0)[1] for t, b in self.buffers.items()})
        persistence.remove_journal(folder)
        self._marks = {t: b.accepted for t, b in self.buffers.items()}
        self._saved_accepted = 0
        self.get_logger().info(f'resumed {n} samples of an interrupted session from {folder} '
                               f'({", ".join(f"{t}: {len(b)}" for t, b in self.buffers.items())})')

    def flush_journal(self) -> None:
        """Write the samples accepted since the last flush to the journal (timer)."""
        with self._io_lock:
            new, ends = {}, {}
            starts = dict(self._marks)
            for topic, b in self.buffers.items():
                ends[topic], new[topic], _ = b.since(self._marks[topic])
                self.gaps[topic].update(new[topic].stamps)
            self._marks = ends
            if self.journal is None or not any(len(s.stamps) for s in new.values()):
                return
            try:
                self.journal.append(new)
            except (OSError, BagError) as e:
                self._journal_failed(e)
                return
            self._chunk_marks.append((self.journal.next_seq - 1, starts, ends))
            if len(self._chunk_marks) >= persistence.MERGE_AFTER:
                self._merge_journal()

    def _journal_failed(self, error: Exception) -> None:
        """Move the journal to the fallback folder and write every held sample there."""
        self._storage_failed('write the sample journal', error)
        self.journal = persistence.SampleJournal(persistence.new_journal_path(
            self.fallback_dir(), self.get_name(), self.config_key))
        self._chunk_marks = []
        held = {t: b.since(0)[1] for t, b in self.buffers.items()}
        self.journal.append(held)

    def _merge_journal(self) -> None:
        """Merge the small chunks into one bag from the samples still held (io lock held)."""
        (seq0, first, _), (seq1, _, last) = self._chunk_marks[0], self._chunk_marks[-1]
        self._chunk_marks = []
        streams = {}
        for topic, b in self.buffers.items():
            _, streams[topic], complete = b.since(first[topic], last[topic])
            if not complete:
                return  # overwritten or forgotten meanwhile: leave the chunks as they are
        self.journal.merge(streams, seq0, seq1)
