"""
The view of ``coreg watch``: coreg_node's statuses as plain data, and the dashboard of them.

The node publishes one ``diagnostic_msgs/DiagnosticStatus`` per concern, named
``<node>: coregistration``, ``<node>: guidance`` (keys of ``coreg_ros.core.live.guidance``) and
``<node>: watchdog`` (keys of ``coreg_ros.core.live.watchdog``). ``DashboardState`` gathers the
latest of each; ``render`` draws them with rich: the live sample counts, the σ each parameter
would have now against the targets as bars, the suggested next motion, and the calibration and
watchdog states. Pure functions, testable without ROS; rich is imported only inside them. The
command (subscribing, refreshing) is ``coreg_ros.cli.watch``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
import math
import time
from typing import Optional

from coreg_ros.core.live.guidance import keys as g
from coreg_ros.core.live.watchdog import keys as w

#: Name suffix of the node's main status (``coreg_ros.ros.node``).
CALIBRATION_STATUS = 'coregistration'
#: Name suffix of the node's noise status (``coreg_ros.ros.live_noise``).
NOISE_STATUS = 'noise'
#: Width of a σ bar, cells; the bar spans 0.1× to 100× the target on a log scale.
BAR_WIDTH = 24
BAR_DECADES = (-1.0, 2.0)
LEVEL_STYLES = {0: 'green', 1: 'yellow', 2: 'red', 3: 'magenta'}
LEVEL_TEXT = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}


@dataclass(frozen=True)
class Status:
    """
    One ``diagnostic_msgs/DiagnosticStatus`` as plain data.

    Attributes
    ----------
    name : str
    level : int
        0 OK, 1 WARN, 2 ERROR, 3 STALE.
    message : str
    values : dict of str to str

    """

    name: str
    level: int
    message: str
    values: dict = field(default_factory=dict)

    @classmethod
    def from_msg(cls, status) -> Status:
        """From a ``DiagnosticStatus`` message (its level is a one-byte ``bytes`` in rclpy)."""
        level = status.level
        if isinstance(level, (bytes, bytearray)):
            level = level[0] if level else 0
        return cls(status.name, int(level), status.message,
                   {kv.key: kv.value for kv in status.values})


@dataclass
class DashboardState:
    """
    What the dashboard shows, gathered from the statuses received so far.

    Attributes
    ----------
    node : str
        The node whose statuses are shown.
    calibration, guidance, watchdog, noise : Status or None
        The latest status of each concern.
    received_at : float or None
        ``time.monotonic()`` of the latest message.
    messages : int
        DiagnosticArray messages received.

    """

    node: str = 'coreg_node'
    calibration: Optional[Status] = None
    guidance: Optional[Status] = None
    watchdog: Optional[Status] = None
    noise: Optional[Status] = None
    received_at: Optional[float] = None
    messages: int = 0

    def update(self, statuses: Iterable[Status], now: Optional[float] = None) -> bool:
        """Take the node's statuses from one message; return whether any was the node's."""
        seen = False
        for status in statuses:
            node, _, what = status.name.partition(': ')
            if node.lstrip('/') != self.node.lstrip('/'):
                continue
            if what == CALIBRATION_STATUS:
                self.calibration = status
            elif what == g.STATUS_NAME:
                self.guidance = status
            elif what == w.STATUS_NAME:
                self.watchdog = status
            elif what == NOISE_STATUS:
                self.noise = status
            else:
                continue
            seen = True
        if seen:
            self.messages += 1
            self.received_at = time.monotonic() if now is None else now
        return seen

    @classmethod
    def from_statuses(cls, statuses: Iterable[Status], node: str = 'coreg_node'
                      ) -> DashboardState:
        """Build a state from one list of statuses."""
        state = cls(node=node)
        state.update(statuses)
        return state


# --------------------------------------------------------------------------- parsing


def _float(text: Optional[str]) -> Optional[float]:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _floats(text: Optional[str]) -> list:
    out = []
    for part in (text or '').split():
        v = _float(part)
        if v is None:
            return []
        out.append(v)
    return out


def sigma_rows(values: dict) -> list:
    """
    (group, σ per axis, target, unit) from the guidance status values, in display order.

    σ and targets in SI units (m, rad, s); the target is None where none is set.
    """
    pos = _float(values.get(g.KEY_TARGET_POSITION))
    rot = _float(values.get(g.KEY_TARGET_ROTATION))
    tim = _float(values.get(g.KEY_TARGET_TIME))
    rows = []
    for key, text in values.items():
        if not key.startswith(g.KEY_SIGMA_PREFIX):
            continue
        name = key[len(g.KEY_SIGMA_PREFIX):]
        sd = _floats(text)
        if not sd:
            continue
        if name == 'time_offset':
            rows.append((name, sd, tim, 's'))
        elif g.is_rotation_group(name):
            rows.append((name, sd, rot, 'rad'))
        else:
            rows.append((name, sd, pos, 'm'))
    return rows


def _shown(value: float, unit: str) -> str:
    if unit == 'm':
        return f'{value * 1e3:.3g}'
    if unit == 'rad':
        return f'{math.degrees(value):.3g}'
    return f'{value * 1e3:.3g}'


SHOWN_UNIT = {'m': 'mm', 'rad': '°', 's': 'ms'}


def bar(ratio: Optional[float], width: int = BAR_WIDTH) -> tuple[str, str]:
    """
    Draw a σ / target bar on a log scale (0.1× .. 100×) with the target marked; (text, style).

    The style is green within target, yellow within 3×, red beyond; dim without a target.
    """
    if ratio is None or not math.isfinite(ratio) or ratio <= 0:
        return '·' * width, 'dim'
    lo, hi = BAR_DECADES
    frac = (math.log10(ratio) - lo) / (hi - lo)
    filled = max(0, min(width, int(round(frac * width))))
    mark = int(round((0.0 - lo) / (hi - lo) * width))
    cells = ['█' if i < filled else '─' for i in range(width)]
    if 0 <= mark < width:
        cells[mark] = '┃' if mark >= filled else '╋'
    style = 'green' if ratio <= 1.0 else 'yellow' if ratio <= 3.0 else 'red'
    return ''.join(cells), style


# --------------------------------------------------------------------------- rendering


def _level_text(level: Optional[int]):
    from rich.text import Text
    if level is None:
        return Text('—', style='dim')
    return Text(LEVEL_TEXT.get(level, str(level)), style=f'bold {LEVEL_STYLES.get(level, "")}')


def _counts_table(status: Optional[Status]):
    from rich.table import Table
    table = Table(title='streams', title_justify='left', expand=True, show_edge=False)
    for col in ('topic', 'received', 'accepted', 'rejected', 'dropped', 'held'):
        table.add_column(col, justify='left' if col == 'topic' else 'right')
    if status is None:
        table.add_row('(no status yet)', '', '', '', '', '')
        return table
    v = status.values
    topics = [k[:-len(' received')] for k in v if k.endswith(' received')]
    for t in topics:
        table.add_row(t, v.get(f'{t} received', ''), v.get(f'{t} accepted', ''),
                      v.get(f'{t} rejected', ''), v.get(f'{t} dropped oldest', ''),
                      v.get(f'{t} held', ''))
    return table


def _calibration_lines(status: Optional[Status]):
    from rich.text import Text
    text = Text()
    if status is None:
        return Text('calibration: no status yet', style='dim')
    v = status.values
    text.append('paired ')
    text.append(v.get('paired', 'n/a'), style='bold')
    rate = v.get('pairing rate')
    if rate and rate != 'n/a':
        text.append(f' (rate {rate})')
    text.append('   last calibration: ')
    n = v.get('last calibration n_pairs', 'n/a')
    if n in ('n/a', '', None):
        text.append('none yet', style='dim')
    else:
        ok = v.get('last calibration success', '').lower() == 'true'
        text.append('success' if ok else 'not a success', style='green' if ok else 'red')
        text.append(f', {n} pairs, χ²/dof {v.get("last calibration chi2_dof", "n/a")}')
        tau = _float(v.get('last calibration time_offset_s'))
        if tau is not None:
            text.append(f', τ {tau * 1e3:+.3g} ms')
        verdict = v.get('last calibration verdict', '')
        if verdict and verdict != 'n/a':
            text.append(f'\n{verdict}', style='yellow')
    text.append('\n')
    text.append(status.message, style=LEVEL_STYLES.get(status.level, ''))
    return text


def _guidance_panel(status: Optional[Status]):
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text
    if status is None:
        return Panel(Text('no guidance status (the node publishes it while collecting)',
                          style='dim'), title='guidance', title_align='left')
    v = status.values
    table = Table(expand=True, show_edge=False, box=None, pad_edge=False)
    table.add_column('parameter')
    table.add_column('σ x y z', justify='right')
    table.add_column('σ / target', justify='left', no_wrap=True)
    table.add_column('target', justify='right')
    for name, sd, target, unit in sigma_rows(v):
        shown = ' '.join(_shown(s, unit) for s in sd) + f' {SHOWN_UNIT[unit]}'
        ratio = None if target is None else max(sd) / target
        cells, style = bar(ratio)
        target_text = 'none' if target is None else f'{_shown(target, unit)} {SHOWN_UNIT[unit]}'
        table.add_row(g.GROUP_TITLES.get(name, name), shown, Text(cells, style=style),
                      target_text)
    ready = v.get(g.KEY_READY, 'false') == 'true'
    head = Text()
    head.append('READY' if ready else 'collecting', style='bold green' if ready else 'bold')
    head.append(f'   pairs {v.get(g.KEY_PAIRS, "n/a")}')
    dur = _float(v.get(g.KEY_DURATION))
    if dur is not None:
        head.append(f' over {dur:.0f} s')
    worst = v.get(g.KEY_WORST)
    if worst:
        group, _, axis = worst.partition(' ')
        worst = f'{g.GROUP_TITLES.get(group, group)} {axis}'.strip()
        head.append(f'   worst {worst} at {v.get(g.KEY_WORST_RATIO, "?")}× target')
    nxt = Text()
    nxt.append('next: ', style='bold')
    nxt.append(v.get(g.KEY_NEXT_TEXT, 'n/a'), style='cyan')
    after = _float(v.get(g.KEY_NEXT_RATIO))
    if after is not None and not ready:
        nxt.append(f'  (worst then {after:.3g}× target)', style='dim')
    return Panel(Group(head, table, nxt), title='guidance', title_align='left')


def _watchdog_panel(status: Optional[Status]):
    from rich.console import Group
    from rich.panel import Panel
    from rich.text import Text
    if status is None:
        return Panel(Text('no watchdog status (it starts once a calibration exists)',
                          style='dim'), title='watchdog', title_align='left')
    v = status.values
    head = Text()
    head.append_text(_level_text(status.level))
    stat, thr = _float(v.get(w.KEY_STATISTIC)), _float(v.get(w.KEY_THRESHOLD))
    head.append(f'   pairs checked {v.get(w.KEY_CHECKED, "n/a")}')
    if stat is not None and thr:
        frac = max(0.0, min(1.0, stat / thr))
        n = int(round(frac * 16))
        head.append('   cusum ')
        head.append('█' * n + '─' * (16 - n), style='red' if frac >= 1 else 'yellow'
                    if frac > 0.5 else 'green')
        head.append(f' {stat:.3g} / {thr:.3g}')
    mean = _float(v.get(w.KEY_MEAN_D2))
    if mean is not None:
        head.append(f'   residual/noise {mean:.2f}')
    lines = [head, Text(v.get(w.KEY_MESSAGE, status.message),
                        style=LEVEL_STYLES.get(status.level, ''))]
    change = v.get(w.KEY_CHANGE, 'none')
    if change not in ('none', '', None):
        sizes = Text('change: ', style='bold')
        sizes.append(w.KIND_TEXT.get(change, change))
        for key, unit in ((w.KEY_TRANSLATION, 'mm'), (w.KEY_ROTATION, '°'),
                          (w.KEY_CLOCK, 'ms'), (w.KEY_NOISE, '× noise')):
            val = v.get(key, 'n/a')
            if val != 'n/a':
                sizes.append(f'   {val} {unit}')
        lines.append(sizes)
    return Panel(Group(*lines), title='watchdog', title_align='left')


def _noise_panel(status: Optional[Status]):
    """Each device's noise: measured while still, stated, in use (and from where)."""
    from rich.console import Group
    from rich.panel import Panel
    from rich.text import Text
    if status is None:
        return Panel(Text('no noise status yet', style='dim'), title='noise', title_align='left')
    v = status.values
    lines = [Text(status.message, style=LEVEL_STYLES.get(status.level, ''))]
    for d in 'AB':
        row = Text(f'{d}  ', style='bold')
        for label, key in (('still', 'measured'), ('stated', 'stated'), ('in use', 'used')):
            pos = _floats(v.get(f'{d} {key} position sigma m'))
            rot = _floats(v.get(f'{d} {key} rotation sigma rad'))
            if not pos:
                continue
            row.append(f'{label} σ ')
            row.append(' '.join(f'{p * 1e3:.3g}' for p in pos) + ' mm')
            if rot:
                row.append(', ' + ' '.join(f'{r * 1e3:.3g}' for r in rot) + ' mrad')
            row.append('   ')
        row.append(f'({v.get(f"{d} source", "n/a")}; still {v.get(f"{d} still seconds", "0")} s)',
                   style='dim')
        lines.append(row)
    return Panel(Group(*lines), title=f'noise ({v.get("noise", "stated")})', title_align='left')


def render(state: DashboardState, now: Optional[float] = None):
    """
    Build the dashboard as a rich renderable (a group of panels).

    Parameters
    ----------
    state : DashboardState
        The latest status received.
    now : float, optional
        ``time.monotonic()`` now, to show the age of the last message.

    """
    from rich.console import Group
    from rich.panel import Panel
    from rich.text import Text
    now = time.monotonic() if now is None else now
    head = Text()
    head.append(f'coreg watch: {state.node}', style='bold')
    if state.received_at is None:
        head.append('   waiting for /diagnostics …', style='yellow')
    else:
        age = max(0.0, now - state.received_at)
        head.append(f'   {state.messages} updates, last {age:.1f} s ago',
                    style='red' if age > 5.0 else 'dim')
    top = Panel(Group(_counts_table(state.calibration), _calibration_lines(state.calibration)),
                title='calibration', title_align='left')
    return Group(head, top, _guidance_panel(state.guidance), _watchdog_panel(state.watchdog),
                 _noise_panel(state.noise))


def render_text(state: DashboardState, width: int = 100, now: Optional[float] = None) -> str:
    """Render the dashboard as plain text (for tests and ``--once`` without a terminal)."""
    from rich.console import Console
    console = Console(width=width, record=True, file=_Null(), color_system=None)
    console.print(render(state, now))
    return console.export_text()


class _Null:

    def write(self, _text: str) -> int:
        return 0

    def flush(self) -> None:
        pass
