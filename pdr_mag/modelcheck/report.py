"""The human report of a diagnosis: Markdown plus PNG plots (matplotlib, the optional ``report`` extra).

Plots (before = baseline, after = final model): the residual norm against time, heading, measured field
strength and angular rate; the measured and simulated field strength against time.  matplotlib is
imported only inside :func:`write_report`; without it :class:`ReportUnavailable` is raised.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pdr_mag.conventions import heading_deg_from_quat, quat_slerp
from pdr_mag.modelcheck.diagnosis import Diagnosis
from pdr_mag.modelcheck.identify import angular_rate
from pdr_mag.modelcheck.predict import simulate_mag


class ReportUnavailable(RuntimeError):
    """matplotlib is not installed."""


def _series(summary):
    p, f = summary.problem, summary.fit
    pred = simulate_mag(p, f)
    res = p.mag - pred
    q = quat_slerp(p.track.t, p.track.quat, p.t)
    rate_track = angular_rate(p.track.t, p.track.quat)
    rate = np.interp(p.t, 0.5 * (p.track.t[1:] + p.track.t[:-1]), rate_track)
    return {
        "t": p.t,
        "res": np.linalg.norm(res, axis=1),
        "heading": heading_deg_from_quat(q),
        "strength": np.linalg.norm(p.mag - np.asarray(f.linear["hard_iron"]), axis=1),
        "strength_sim": np.linalg.norm(pred - np.asarray(f.linear["hard_iron"]), axis=1),
        "rate": rate,
    }


def _accelerometer_lines(acc: dict) -> list[str]:
    if not acc.get("named"):
        return []
    b = np.degrees(np.linalg.norm(acc["rad_per_s"]))
    return [f"- gyro_bias named by the accelerometer (the drift of gravity in the gyro frame): {b:.2f} °/s, "
            f"T² {acc['t2']} > {acc['threshold']}, in the orientation from the start; the final model's gap "
            f"{acc['gap_with']:.3f} µT with it, {acc['gap_raw_gyro']:.3f} µT along the raw gyro"]


def _motion_text(m: dict) -> str:
    if not m:
        return "—"
    return (f"mean up axis {m['up_axis_d']} (device axes), tilted from it by {m['tilt_rms_deg']}° rms; "
            f"the field swept device axis {m['least_swept_axis_d']} least ({m['least_swept_deg']}°); angular "
            f"rate {m['rate_rms_rad_per_s']} rad/s rms; {m['duration_s']} s; gap {m['gap_uT']} µT over a "
            f"white noise of {m['white_noise_uT']} µT.")


def write_report(diagnosis: Diagnosis, out_dir, title: str = "recording") -> Path:
    """Write ``report.md`` and its plots into ``out_dir``; returns the Markdown path."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        msg = "matplotlib is needed for the report (pip install 'pdr_mag[report]')"
        raise ReportUnavailable(msg) from exc
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    before = _series(diagnosis.baseline)
    after = _series(diagnosis.final)
    kw_b = dict(s=2, alpha=0.5, color="tab:red", label=f"baseline ({diagnosis.baseline.gap:.2f} µT)")
    kw_a = dict(s=2, alpha=0.5, color="tab:blue", label=f"final ({diagnosis.final.gap:.2f} µT)")
    # the final estimates give absolute times (the recording's clock): the time axis names its origin
    time_label = f"time since {diagnosis.baseline.problem.t_origin:.3f} s (first magnetometer sample), s"

    plots = []
    for key, xlabel, fname in (
        ("t", time_label, "residual_vs_time.png"),
        ("heading", "heading of the orientation track (deg, arbitrary reference)", "residual_vs_heading.png"),
        ("strength", "measured field strength |m − b| (µT)", "residual_vs_strength.png"),
        ("rate", "angular rate (rad/s)", "residual_vs_rate.png"),
    ):
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.scatter(before[key], before["res"], **kw_b)
        ax.scatter(after[key], after["res"], **kw_a)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("|measured − simulated| (µT)")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.legend(loc="upper right", markerscale=4)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=90)
        plt.close(fig)
        plots.append((xlabel, fname))
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot(after["t"], after["strength"], lw=0.8, color="k", label="measured")
    ax.plot(before["t"], before["strength_sim"], lw=0.8, color="tab:red", label="simulated, baseline")
    ax.plot(after["t"], after["strength_sim"], lw=0.8, color="tab:blue", label="simulated, final")
    ax.set_xlabel(time_label)
    ax.set_ylabel("|m − b| (µT)")
    ax.legend(loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "field_strength.png", dpi=90)
    plt.close(fig)
    plots.append(("field strength", "field_strength.png"))

    d = diagnosis.to_dict()
    lines = [
        f"# Model check: {title}",
        "",
        f"Orientation from **{d['orientation']}**, {d['n_samples']} magnetometer samples over "
        f"{d['duration_s']:.1f} s. Gap = {d['gap_metric']}.",
        "",
        f"- baseline ({', '.join(d['baseline']['effects'])}): gap **{d['baseline']['gap']:.3f} µT**",
        f"- missing effects, in the order added: **{', '.join(d['missing_effects']) or 'none'}**",
        f"- final ({', '.join(d['final']['effects'])}): gap **{d['final']['gap']:.3f} µT**",
        *_accelerometer_lines(d.get("gyro_bias_from_accelerometer") or {}),
        "",
        "## Candidates by round",
        "",
        "| round | effect | gap (µT) | score (ΔBIC) | null: statistic / threshold | significant | estimate |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for rnd in d["rounds"]:
        for c in rnd:
            est = ", ".join(f"{k}={v}" for k, v in c["estimate"].items() if k != "windows_s")
            null = "—" if c.get("null") is None else f"{c['null']['statistic']} / {c['null']['threshold']}"
            lines.append(f"| {c['round']} | {c['effect']} | {c['gap']} | {c['score']} | {null} | "
                         f"{'yes' if c['significant'] else 'no'} | {est} |")
    lines += ["", "## What this motion can reveal", "",
              f"Motion: {_motion_text(d.get('motion', {}))}", "",
              "| effect | status | identified directions | why not (the rest) | would be revealed by |",
              "| --- | --- | --- | --- | --- |"]
    for e, v in d.get("identifiability", {}).items():
        n = len(v["directions"])
        dirs = f"{v['identifiable_directions']} of {n}" if n else "—"
        lines.append(f"| {e} | {v['status'].replace('_', ' ')} | {dirs} | {v['reason'] or '—'} "
                     f"| {v['reveal'] or '—'} |")
    lines += ["", "Null: the candidate's statistic (ln RSS ratio; along the field for effects that change "
              "its strength) on the recording, and the threshold it had to beat on surrogates of the "
              "recording with nothing missing (orientation error and noise only).", "",
              "## Final estimates", ""]
    for name, est in d["final"]["estimate"].items():
        lines.append(f"- `{name}`: {est}")
    lines += ["", "## Residuals before and after", ""]
    for label, fname in plots:
        lines += [f"![{label}]({fname})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
