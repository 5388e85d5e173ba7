"""
The samples of coreg_node: intake, bounded buffers, counts, the journal and the sample bags.

``SampleStore`` takes the pose messages (the callbacks of the node's subscriptions: raw, in
bulk, through ``ros.raw_intake``, or one deserialised message per callback), validates and
keeps them in one ``StreamBuffer`` per topic, and counts what it refused, what the middleware
lost and what is missing from the stamps. The accepted samples are journalled to rosbag2
chunks in ``storage_dir`` (``persistence.SampleJournal``; the node's timer calls
``flush_journal`` every ``FLUSH_PERIOD`` s), so a kill loses at most that; a journal left by a
killed session is reported at start-up and resumed with ``resume_samples``. ``save_samples``
writes the held samples to a bag; on shutdown the samples not yet saved go to one. A failing
``storage_dir`` sends the samples to a named temporary folder and /diagnostics to ERROR
(``Alerts.storage_failed``).

Threads: the callbacks run in the streams thread; everything else in the services thread (and
``save_on_shutdown`` in the main thread once that has ended). The buffers lock themselves;
disk writes take ``io_lock``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
import sys
import tempfile
import threading
import time
from typing import Optional

from coreg_ros.core.errors import BagError, CoregError
from coreg_ros.ros import persistence
from coreg_ros.ros.alerts import Alerts, os_reason
from coreg_ros.ros.buffer import GapCounter, reason_hint, SequenceCounter, StreamBuffer
from coreg_ros.ros.interface import POSE_TYPE
from coreg_ros.ros.messages import pose_stamped_values
from coreg_ros.ros.parameters import NodeConfig
from coreg_ros.ros.raw_intake import RawIntake
from geometry_msgs.msg import PoseStamped

#: Seconds between two writes of the new samples to the journal: what a kill can lose.
FLUSH_PERIOD = 0.5


class SampleStore:
    """
    The pose samples of the node, in memory and on disk.

    Parameters
    ----------
    config : NodeConfig
        The topics (``settings``), ``buffer_capacity``, ``storage_dir`` and ``resume_samples``.
    node_name : str
        The node's name: it names the journal and the fallback folder.
    config_key : str
        ``persistence.config_key`` of the configuration (names the journal).
    alerts : Alerts
        Throttled warnings and the storage error.
    logger : rclpy.impl.rcutils_logger.RcutilsLogger
        The node's logger.
    io_lock : threading.Lock
        Taken around the node's disk writes (journal, bags, the stored result).
    raw : bool
        Take the messages raw and in bulk (``RawIntake``); False: one deserialised message
        per callback.

    Attributes
    ----------
    topics : tuple of str
        A's topic, then B's.
    buffers : dict of str to StreamBuffer
        The held samples and their counts, per topic.
    gaps : dict of str to GapCounter
        Messages missing from the stamps, per topic.
    lost : dict of str to int
        Messages the middleware reported lost, per topic.
    sequences : dict of str to SequenceCounter
        Messages lost on the way, from the publishers' sequence numbers, per topic.
    intake : RawIntake or None
        The bulk intake (None on the plain path).
    journal : persistence.SampleJournal or None
        This session's journal.
    left_over : list of Path
        Journals of interrupted sessions, not resumed.

    """

    def __init__(self, config: NodeConfig, node_name: str, config_key: str, alerts: Alerts,
                 logger, io_lock: threading.Lock, raw: bool = True):
        settings = config.settings
        self.config = config
        self.node_name = node_name
        self.config_key = config_key
        self.alerts = alerts
        self.logger = logger
        self.io_lock = io_lock
        self.topics = (settings.topic_a, *settings.topic_b)
        self.buffers = {t: StreamBuffer(config.buffer_capacity) for t in self.topics}
        self.gaps = {t: GapCounter() for t in self.topics}
        self.lost = dict.fromkeys(self.topics, 0)   # middleware message-lost events
        created = time.time_ns()  # before the subscriptions: what is sent after, is for us
        self.sequences = {t: SequenceCounter(created) for t in self.topics}
        self.intake: Optional[RawIntake] = None
        if raw:
            self.intake = RawIntake(self.buffers, self._warn_rejected, self._warn_undecodable,
                                    sequences=self.sequences)
        self.journal: Optional[persistence.SampleJournal] = None
        self.left_over: list = []
        self.last_save_error: Optional[str] = None  # why the last save went to the fallback
        self._rejected_since: dict = {}  # (topic, reason) -> rejections since its last line
        self._saved_accepted = 0        # accepted-sample total at the last bag save
        self._marks = dict.fromkeys(self.topics, 0)  # accepted count at the last flush
        self._chunk_marks: list = []  # (seq, start marks, end marks) of the unmerged chunks
        self._fallback_dir: Optional[str] = None    # named temporary folder if storage fails

    # --- intake (streams thread) ------------------------------------------------------------

    @property
    def raw(self) -> bool:
        """Tell whether the subscriptions take CDR bytes, not deserialised messages."""
        return self.intake is not None

    def callback(self, topic: str) -> Callable:
        """Return the subscription callback of ``topic`` (raw or plain, as ``raw`` says)."""
        if self.intake is not None:
            return self.intake.callback(topic)
        push = self.buffers[topic].push
        sequence = self.sequences[topic].update_one
        time_ns = time.time_ns

        def on_pose(msg: PoseStamped, info: dict) -> None:  # two arguments: rclpy passes info
            # Cheap on purpose: scalars into a preallocated ring, no logging.
            sequence(info)
            stamp, x, y, z, qw, qx, qy, qz = pose_stamped_values(msg)
            reason = push(stamp, time_ns(), x, y, z, qw, qx, qy, qz, msg.header.frame_id)
            if reason is not None:
                self._warn_rejected(topic, reason)

        return on_pose

    def attach(self, topic: str, subscription) -> None:
        """Register the subscription of ``topic`` (the raw intake drains them all together)."""
        if self.intake is not None:
            self.intake.attach(topic, subscription)

    def on_lost(self, topic: str) -> Callable:
        """Return the message-lost event callback of ``topic``'s subscription."""
        def lost(status) -> None:
            self.lost[topic] += int(status.total_count_change)
        return lost

    def loss(self, topic: str) -> tuple:
        """
        Return the messages lost on the way to ``topic``'s subscription and how they were counted.

        From the publisher's sequence numbers where the middleware gives them and one publisher
        sends (exact, the messages before the first one taken included); else the larger of the
        middleware's message-lost events and the holes in the stamps (neither sees messages
        lost before the first one taken).

        Returns
        -------
        lost : int
            Messages lost.
        how : str
            How they were counted, for /diagnostics.

        """
        seq = self.sequences[topic]
        if seq.counting:
            return seq.lost, (f'publication sequence numbers ({seq.between} between messages, '
                              f'{seq.head} before the first)')
        events, stamps = self.lost[topic], self.gaps[topic].missing
        why = seq.why_not or 'no message yet'
        if events >= stamps:
            return events, f"the middleware's message-lost events ({why})"
        return stamps, f'holes in the stamps ({why})'

    def undecodable(self, topic: str) -> int:
        """Messages on ``topic`` that were not a serialized PoseStamped."""
        return 0 if self.intake is None else self.intake.undecodable[topic]

    def _warn_rejected(self, topic: str, reason: str, count: int = 1) -> None:
        """Throttled warning: at most one per topic and reason every WARN_PERIOD seconds."""
        key = (topic, reason)
        self._rejected_since[key] = self._rejected_since.get(key, 0) + count
        if self.alerts.ready(key):
            self.logger.warning(
                f'{topic}: rejected {self._rejected_since[key]} message(s): '
                f'{reason_hint(reason)} (counts in /diagnostics)')
            self._rejected_since[key] = 0

    def _warn_undecodable(self, topic: str, count: int, error: BaseException) -> None:
        """Throttled warning about bytes on a pose topic that are not a PoseStamped."""
        self.alerts.throttled(('undecodable', topic), (
            f'{topic}: {count} message(s) are not a serialized {POSE_TYPE} '
            f'({type(error).__name__}: {error}); a publisher sends raw bytes of another type: '
            f'fix that publisher (counts in /diagnostics)'))

    # --- the held samples -------------------------------------------------------------------

    def accepted_total(self) -> int:
        """Return the samples accepted on every topic since start-up."""
        return sum(b.accepted for b in self.buffers.values())

    def snapshot(self) -> dict:
        """Return copies of the accumulated raw samples: topic -> PoseStream."""
        return {t: b.snapshot() for t, b in self.buffers.items()}

    def forget(self) -> int:
        """Forget the held samples and their journal, start a new one; return how many."""
        with self.io_lock:
            held = sum(len(b) for b in self.buffers.values())
            for b in self.buffers.values():
                b.clear()
            for g in self.gaps.values():
                g.restart()
            self._saved_accepted = self.accepted_total()
            # the journal holds the session's samples: forgotten with them
            self._marks = {t: b.accepted for t, b in self.buffers.items()}
            if self.journal is not None:
                self.journal.remove()
                self.journal = None
        self.start_journal()
        return held

    # --- sample bags --------------------------------------------------------------------------

    def fallback_dir(self) -> str:
        """Return a named temporary folder for what storage_dir cannot take (made once)."""
        if self._fallback_dir is None:
            self._fallback_dir = tempfile.mkdtemp(prefix=f'{self.node_name}_samples_')
            self.logger.error(f'storage_dir failed: samples go to {self._fallback_dir}')
        return self._fallback_dir

    def save_samples(self, report: Optional[Callable[[str], None]] = None) -> Optional[str]:
        """
        Write the held samples to a new bag in storage_dir; None if there are none.

        If storage_dir cannot be written, the bag goes to a named temporary folder instead
        and ``last_save_error`` says why (diagnostics go ERROR).

        Parameters
        ----------
        report : callable, optional
            Takes the one line saying where the samples went, instead of the node logger
            (which cannot publish to /rosout any more once the context is shut down).

        """
        self.last_save_error = None
        with self.io_lock:
            accepted = self.accepted_total()
            streams = self.snapshot()
            if not any(len(s) for s in streams.values()):
                return None
            try:
                path = persistence.save_samples(self.config.storage_dir, streams)
            except (OSError, BagError) as e:
                self.last_save_error = self.alerts.storage_failed('save the samples', e)
                path = persistence.save_samples(self.fallback_dir(), streams)
            self._saved_accepted = accepted
        line = f'saved {sum(len(s) for s in streams.values())} samples to {path}'
        (report or self.logger.info)(line)
        return str(path)

    def on_save_samples(self, request, response):
        """Answer ``~/save_samples`` (std_srvs/Trigger): the bag's path, or why not."""
        try:
            path = self.save_samples()
        except CoregError as e:
            response.success, response.message = False, str(e)
            return response
        if path is None:
            response.success, response.message = False, 'no samples to save yet'
        elif self.last_save_error:
            response.success = False
            response.message = f'{self.last_save_error}; the samples were saved to {path}'
        else:
            response.success, response.message = True, str(path)
        return response

    def save_on_shutdown(self) -> bool:
        """
        Save the samples received since the last save, if any (called on shutdown).

        Returns False if they could not be saved anywhere (the journal is then kept).
        """
        def report(line):
            print(f'coreg_node: {line}', file=sys.stderr)

        saved = True
        if self.accepted_total() != self._saved_accepted:
            try:
                self.save_samples(report=report)
                if self.last_save_error:
                    report(self.last_save_error)
            except Exception as e:  # shutting down: report, do not raise over the real exit
                report(f'could not save the samples on shutdown: {os_reason(e)}')
                saved = False
        if saved and self.journal is not None:
            self.journal.remove()  # a clean end: the samples are in the bag
        elif self.journal is not None:
            report(f'the samples are still in the journal {self.journal.folder}')
        return saved

    # --- journal ----------------------------------------------------------------------------

    def start_journal(self) -> None:
        """Open this session's journal; resume or report a journal a killed session left."""
        storage, name, key = self.config.storage_dir, self.node_name, self.config_key
        left = persistence.left_over_journals(storage, name, key)
        if self.journal is not None:
            left = [p for p in left if p != self.journal.folder]
        if left and self.config.resume_samples and self.accepted_total() == 0:
            try:
                self._resume(left[-1])
                left = left[:-1]
            except Exception as e:
                self.logger.error(f'cannot resume the journal {left[-1]}: '
                                  f'{os_reason(e)}; it is kept, starting afresh')
        self.left_over = left
        for path in left:
            self.logger.warning(
                f'an interrupted session (the node was killed) left samples in {path}; '
                f'restart with resume_samples:=true to continue from them (the newest)')
        if self.journal is None:
            try:
                self.journal = persistence.SampleJournal(
                    persistence.new_journal_path(storage, name, key))
            except (OSError, BagError) as e:
                self.alerts.storage_failed('write the sample journal', e)
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
            self.config.storage_dir, self.node_name, self.config_key))
        self.journal.append({t: b.since(0)[1] for t, b in self.buffers.items()})
        persistence.remove_journal(folder)
        self._marks = {t: b.accepted for t, b in self.buffers.items()}
        self._saved_accepted = 0
        self.logger.info(f'resumed {n} samples of an interrupted session from {folder} '
                         f'({", ".join(f"{t}: {len(b)}" for t, b in self.buffers.items())})')

    def flush_journal(self) -> None:
        """Write the samples accepted since the last flush to the journal (timer)."""
        with self.io_lock:
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
        self.alerts.storage_failed('write the sample journal', error)
        self.journal = persistence.SampleJournal(persistence.new_journal_path(
            self.fallback_dir(), self.node_name, self.config_key))
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
