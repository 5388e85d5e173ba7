"""
Render ``~/uncertainty_markers`` as RViz would draw them (Hoff & Vincent's Fig. 1) with matplotlib.

Each marker is drawn from the message geometry alone, as RViz interprets it: a SPHERE is the unit
sphere of diameter 1 scaled by ``scale`` along its own axes, rotated by ``pose.orientation`` and
moved to ``pose.position``; a TRIANGLE_LIST is its triangles. One panel per namespace
(``base_to_base``, ``tool_to_marker``, ``fused``), centred on the frame, since the three live in
different frames and differ in size by orders of magnitude.

By default the MarkerArray is built offline by the node's own code
(``coreg_ros.ros.uncertainty_outputs.pose_markers``) from a calibration of a simulated
recording (Hoff-like devices: A 0.1 mm / 2 mrad, B 2 mm / 0.8 mrad) and one fused pair, for
which B's orientation is made weak about B's base z axis (3 mrad), as Hoff's oblong target
pattern, so that the cones of the other two axes are elongated as in his Fig. 1; with
``--live`` it is received from a running coreg_node (same ``ROS_DOMAIN_ID``). Millimetre
ellipsoids and milliradian cones are invisible beside a 10 cm axis, so each panel is magnified
(``--gain``; default: per panel the largest 3σ semi-axis becomes a quarter of the axis length
and the widest cone a half-angle of about 11°) and the true sizes are printed.

Run: ``python bench/render_markers.py [--out docs/uncertainty_markers.png] [--live]``
"""

from __future__ import annotations

import argparse
import sys

from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.live.fusion import fused_stream, FusionCalibration
from coreg_ros.core.settings import Settings
from coreg_ros.ros.uncertainty_outputs import AXIS_LENGTH, pose_markers
from coreg_ros.sim import simulate_pairs
import numpy as np

#: Device A: position 0.1 mm, orientation 2 mrad; device B: 2 mm, 0.8 mrad (Hoff-like).
SIGMA_A = (1.0e-4, 2.0e-3)
SIGMA_B = (2.0e-3, 8.0e-4)
TITLES = {'base_to_base': 'T0: A base in B base (frame_base_b)',
          'tool_to_marker': 'T1: B marker in A tool (frame_tool)',
          'fused': 'fused pose: B marker in B base (frame_base_b)'}


#: B's noise for the fused panel: orientation weak about B's base z (Hoff's oblong pattern).
COV_B_FUSED = np.diag([SIGMA_B[0] ** 2] * 3 + [4.0e-4 ** 2, 4.0e-4 ** 2, 3.0e-3 ** 2])


def scenario(seed: int = 7, n_pairs: int = 150):
    """Return the three uncertain poses (T0, T1, one fused pair) of a simulated rig."""
    rng = np.random.default_rng(seed)
    pairs, _, _ = simulate_pairs(rng, n_pairs, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result = calibrate(pairs, Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B))
    fused = fused_stream(FusionCalibration.from_result(result), pairs, SIGMA_A, COV_B_FUSED)
    return {'base_to_base': result.base_to_base, 'tool_to_marker': result.tool_to_marker,
            'fused': fused.pose(-1)}


def auto_gains(pose) -> tuple[float, float]:
    """Gains: largest 3σ semi-axis = axis length / 4; widest cone: tan(half-angle) = 0.2."""
    ell = unc.ellipsoid_axes(np.asarray(pose.covariance)[0:3, 0:3])
    widest = max(float(np.tan(c.half_angles[0])) for c in unc.axis_cones(pose))
    return float(0.25 * AXIS_LENGTH / ell.semi_axes[0]), 0.2 / widest


def offline_markers(gain=None) -> tuple[list, dict]:
    """Build the markers with the node's code; return (markers, gains per namespace)."""
    from builtin_interfaces.msg import Time

    frames = {'base_to_base': 'device_b_base', 'tool_to_marker': 'device_a_tool',
              'fused': 'device_b_base'}
    markers, gains = [], {}
    for ns, pose in scenario().items():
        gains[ns] = auto_gains(pose) if gain is None else (float(gain), float(gain))
        markers += pose_markers(pose, frames[ns], Time(), ns, magnification=gains[ns][0],
                                cone_magnification=gains[ns][1])
    return markers, gains


def live_markers(timeout: float) -> list:
    """Receive the latched MarkerArray of a running coreg_node."""
    from coreg_ros.ros.session import RosSession
    from coreg_ros.ros.tools import wait_for_message
    from coreg_ros.ros.uncertainty_outputs import MARKER_QOS
    from visualization_msgs.msg import MarkerArray

    with RosSession('render_markers', signals=False) as session:
        msg = wait_for_message(session, MarkerArray, '/coreg_node/uncertainty_markers',
                               MARKER_QOS, timeout)
    if msg is None:
        raise SystemExit('no MarkerArray on /coreg_node/uncertainty_markers; is coreg_node '
                         'running (same ROS_DOMAIN_ID) with a calibration?')
    return list(msg.markers)


def sphere_surface(marker, n: int = 40):
    """Surface (X, Y, Z) of a SPHERE marker as RViz draws it."""
    u = np.linspace(0.0, 2.0 * np.pi, n)
    v = np.linspace(0.0, np.pi, n // 2)
    unit = np.stack([np.outer(np.cos(u), np.sin(v)), np.outer(np.sin(u), np.sin(v)),
                     np.outer(np.ones_like(u), np.cos(v))], axis=-1)  # radius 1
    s = np.array([marker.scale.x, marker.scale.y, marker.scale.z]) / 2.0  # diameter -> radius
    o = marker.pose.orientation
    R = quat.to_matrix(np.array([o.w, o.x, o.y, o.z]))
    p = marker.pose.position
    pts = (unit * s) @ R.T + np.array([p.x, p.y, p.z])
    return pts[..., 0], pts[..., 1], pts[..., 2]


def draw(markers: list, gains: dict, path: str) -> None:
    """Draw one 3-D panel per namespace and save a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    by_ns = {}
    for m in markers:
        if m.action == m.ADD:
            by_ns.setdefault(m.ns, []).append(m)
    names = [ns for ns in TITLES if ns in by_ns] + [ns for ns in by_ns if ns not in TITLES]
    fig = Figure(figsize=(5.2 * len(names), 5.6), dpi=110)
    FigureCanvasAgg(fig)
    for k, ns in enumerate(names):
        ax = fig.add_subplot(1, len(names), k + 1, projection='3d')
        gain = gains.get(ns, (1.0, 1.0))
        centre, lines, dirs = None, [], []
        for m in sorted(by_ns[ns], key=lambda m: m.id):
            rgba = (m.color.r, m.color.g, m.color.b, m.color.a)
            if m.type == m.SPHERE:
                X, Y, Z = sphere_surface(m)
                ax.plot_surface(X, Y, Z, color=rgba[:3], alpha=0.45, linewidth=0.2,
                                edgecolor=(0.3, 0.3, 0.3, 0.25), shade=True)
                p = m.pose.position
                centre = np.array([p.x, p.y, p.z])
                s = np.array([m.scale.x, m.scale.y, m.scale.z]) / 2.0
                lines.append('ellipsoid 3σ semi-axes ' + ', '.join(
                    f'{v / gain[0] * 1e3:.3g}' for v in np.sort(s)[::-1]) + ' mm')
            elif m.type == m.TRIANGLE_LIST:
                tri = np.array([[q.x, q.y, q.z] for q in m.points]).reshape(-1, 3, 3)
                ax.add_collection3d(Poly3DCollection(tri, facecolor=rgba[:3], alpha=0.55,
                                                     edgecolor=(*rgba[:3], 0.9),
                                                     linewidth=0.3))
                apex, rim = tri[0, 0], tri[:, 1]
                axis = rim.mean(axis=0) - apex
                dirs.append(axis / np.linalg.norm(axis))
                ax.plot(*np.stack([apex, apex + 1.25 * axis]).T, color=rgba[:3], lw=1.2)
                ax.text(*(apex + 1.32 * axis), 'xyz'[m.id - 1], color=rgba[:3], fontsize=11,
                        fontweight='bold')
                radius = np.linalg.norm(rim - rim.mean(axis=0), axis=1)
                half = np.arctan([radius.max() / np.linalg.norm(axis) / gain[1],
                                  radius.min() / np.linalg.norm(axis) / gain[1]])
                lines.append(f'{"xyz"[m.id - 1]} cone 3σ half-angles {half[0] * 1e3:.3g} × '
                             f'{half[1] * 1e3:.3g} mrad')
                if centre is None:
                    centre = apex
        r = 1.35 * AXIS_LENGTH
        ax.set_xlim(centre[0] - r, centre[0] + r)
        ax.set_ylim(centre[1] - r, centre[1] + r)
        ax.set_zlim(centre[2] - r, centre[2] + r)
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel('x [m]', fontsize=8)
        ax.set_ylabel('y [m]', fontsize=8)
        ax.set_zlabel('z [m]', fontsize=8)
        ax.tick_params(labelsize=6)
        # look along a diagonal of the frame's own axes, so that all three show alike (the one
        # from highest above, so the z axis of the plot stays up)
        if len(dirs) == 3:
            signs = np.array([[a, b, c] for a in (1, -1) for b in (1, -1) for c in (1, -1)])
            diagonals = signs @ np.array(dirs) / np.sqrt(3.0)
            view = diagonals[np.argmax(diagonals[:, 2])]
            ax.view_init(elev=float(np.degrees(np.arcsin(view[2]))),
                         azim=float(np.degrees(np.arctan2(view[1], view[0]))))
        else:
            ax.view_init(elev=22, azim=-55)
        frame = by_ns[ns][0].header.frame_id
        ax.set_title(f'{TITLES.get(ns, ns)}\nellipsoid ×{gain[0]:.3g}, cones ×{gain[1]:.3g} '
                     f'(frame {frame})', fontsize=9)
        ax.text2D(0.02, -0.02, '\n'.join(lines), transform=ax.transAxes, fontsize=7,
                  va='top', family='monospace')
    fig.suptitle('~/uncertainty_markers as RViz draws them: 3σ position ellipsoid (SPHERE) '
                 'and axis cones (TRIANGLE_LIST), Hoff & Vincent Fig. 1', fontsize=11)
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.17, top=0.86, wspace=0.08)
    fig.savefig(path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--out', default='docs/uncertainty_markers.png')
    parser.add_argument('--gain', type=float, help='one magnification for every panel '
                        '(default: per panel, largest semi-axis = axis length / 4)')
    parser.add_argument('--live', action='store_true',
                        help='draw the MarkerArray of a running coreg_node instead')
    parser.add_argument('--timeout', type=float, default=10.0)
    args = parser.parse_args(argv)
    if args.live:
        markers = live_markers(args.timeout)
        gains = {}  # the node's marker_magnification is not in the message: sizes as drawn
    else:
        markers, gains = offline_markers(args.gain)
    draw(markers, gains, args.out)
    print(f'wrote {args.out} ({len(markers)} markers)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
