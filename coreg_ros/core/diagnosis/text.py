"""The diagnosis report as text (what ``coreg diagnose`` prints and the HTML report shows)."""

from __future__ import annotations

from coreg_ros.core.diagnosis.report import DiagnosisReport


def floor_named(text: str, estimated: bool) -> str:
    """
    Name the noise a diagnosis' text measured against: the estimated one with ``noise: auto``.

    The diagnosis measures every gap against the noise it was given, which its text calls
    stated; with ``noise: auto`` that is the noise estimated with the calibration.
    """
    if not estimated:
        return text
    return text.replace('the stated noise', 'the estimated noise').replace(
        'stated floor', 'estimated floor')


def format_diagnosis(report: DiagnosisReport) -> str:
    """Human-readable summary of a diagnosis report."""
    return floor_named(_lines(report), report.noise is not None)


def _lines(report: DiagnosisReport) -> str:
    """Return the summary in the words of the stated noise (``format_diagnosis``)."""
    lines = [f'verdict: {report.verdict}']
    det = report.detection
    flags = ', '.join(det.flags.raised) or 'none'
    lines.append(f'detect: chi2/dof {det.chi2_per_dof:.3f} (p = {det.p_value:.3g}), '
                 f'Ljung-Box p = {det.ljung_box.p_value:.3g}, gross pairs '
                 f'{det.tails.gross_pairs} (expected '
                 f'{det.tails.expected_gross_pairs:.2g}); flags: {flags}')
    loc = report.location
    ch = ', '.join(f'{k} {v:+.2f}' for k, v in loc.by_channel.items())
    lines.append(f'locate: excess by channel {ch}; largest in {loc.largest}')
    svm = loc.static_vs_moving
    if svm.static.n:
        lines.append(f'        static {svm.static.excess:+.2f} vs moving '
                     f'{svm.moving.excess:+.2f}')
    xc = loc.velocity_xcorr
    lines.append(f'        residual-velocity correlation {xc.linear_at_zero:+.3f} (linear), '
                 f'{xc.angular_at_zero:+.3f} (angular)')
    if report.effects:
        lines.append('effects:')
        for e in report.effects:
            lines.append(f'  {e.name} [{e.kind}]: {e.estimate.text} (held-out gain '
                         f'{e.held_out_gain:.1f} nats, {e.blocks_improved}/{e.blocks} '
                         f'blocks)')
    else:
        lines.append('effects: none')
    if report.not_separable:
        lines.append('not separable with this motion: '
                     + '; '.join(' vs '.join(p) for p in report.not_separable))
    lines += _gap_lines(report)
    ne = report.noise_excess
    if ne is not None:
        lines.append(f'noise excess: {ne.text}; largest at '
                     f'{ne.largest_in_time_s[0]:.0f}-{ne.largest_in_time_s[1]:.0f} s')
    if report.stamps is not None:
        for dev in report.stamps.devices:
            lines.append(f'stamps {dev.device}: {dev.text}')
    return '\n'.join(lines)


def _gap_lines(report: DiagnosisReport) -> list:
    """Return the lines of the gap before and after at the stated noise, and the pairs aside."""
    after = report.gap_after
    b, a = report.gap_before.stated.counted, after.stated.counted
    line = (f'gap (held out, at the stated noise): chi2/dof '
            f'{b.chi2_per_dof_at_stated_noise:.3f} -> {a.chi2_per_dof_at_stated_noise:.3f}'
            f'; position RMS {b.rms_position_mm:.3f} -> {a.rms_position_mm:.3f} mm '
            f'(stated floor {a.stated_floor_position_mm:.3f} mm)')
    if a.rms_rotation_deg is not None:
        line += (f'; rotation RMS {b.rms_rotation_deg:.3f} -> {a.rms_rotation_deg:.3f} deg '
                 f'(stated floor {a.stated_floor_rotation_deg:.3f} deg)')
    line += f'; share of the excess explained {after.share_of_excess_explained * 100:.0f} %'
    if not after.rms_moved:
        line += ' (the RMS did not move: nothing explained)'
    lines = [line]
    excl = after.stated.excluded_pairs
    if excl.count:
        lines.append(f'  {excl.count} pairs ({excl.share * 100:.1f} %) set aside as '
                     f'outliers, counted as unexplained (all pairs: position RMS '
                     f'{after.stated.all_pairs.rms_position_mm:.3f} mm)')
    return lines
