"""The console's summary of a ``pdr-mag replay`` run: one line per figure a user looks at first (what was
read, the calibration and prior, the events and drift episodes, the heading against the truth and the
phone's own, the magnetometer's latency, the streams' gaps, what was dropped, the throughput), from the
run's summary dict (the ``replay --json`` object, :meth:`replay.run.ReplayRun.summary`)."""

from __future__ import annotations

from collections import Counter

from pdr_mag.episodes import Episode, worst


def summary_table(summary: dict) -> str:
    """The human-readable table printed at the end of ``pdr-mag replay``."""
    rows = [
        ("recording", str(summary.get("source", ""))),
        ("outputs", f"{summary['n_outputs']} over {summary['duration_s']:.1f} s"),
        ("north", summary["north"] if summary["north"] != "magnetic" else
         "magnetic: no place and day known (--latitude, --longitude, --date give the field model)"),
        ("calibration", "given" if summary.get("calibration_given") else "online only"),
        ("prior", _prior_line(summary)),
        ("final cal_state", summary.get("cal_state", "")),
    ]
    rows.append(
        ("rows per cal_state", ", ".join(f"{k} {v}" for k, v in summary.get("cal_state_rows", {}).items()))
    )
    if summary.get("phone_heading_rows"):
        rows.append(("phone's heading", f"{summary['phone_heading_rows']} rows, where pdr_mag's was unknown "
                     "(σ 180°)"))
    kinds = Counter(e["kind"] for e in summary["events"])
    rows.append(("events", ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"))
    cals = summary["calibrations"]
    if cals:
        last = cals[-1]
        off = ", ".join(f"{v:.1f}" for v in last["offset_uT"])
        # an offset the phone stated, or one fitted without the field's norm, knows no field strength
        field = f"field {last['field_uT']:.1f} µT" if last.get("field_uT") else "field not estimated"
        rows.append(("last calibration", f"{last['method']} offset ({off}) µT, {field}"))
    episodes = summary.get("episodes", [])
    kinds = Counter(e["kind"] for e in episodes)
    rows.append(("drift episodes", ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"))
    for i, ep in enumerate(worst([Episode.from_dict(e) for e in episodes]), 1):
        rows.append((f"  worst {i}", ep.describe()))
    rows += _score_rows(summary)
    lag = _latency_line(summary)
    if lag:
        rows.append(("mag latency", lag))
    rows.append(("stream gaps", _gaps_line(summary.get("stream_gaps"))))
    dropped = summary["dropped_samples"]
    rows.append(("dropped samples", ", ".join(f"{k} {v}" for k, v in dropped.items()) or "none"))
    if summary.get("samples_per_s"):
        rows.append(
            (
                "throughput",
                f"{summary['samples_per_s']:.0f} samples/s "
                f"({summary['elapsed_s']:.2f} s: reading, pipeline, sinks)",
            )
        )
    if summary.get("compile_s"):
        what = "numba kernels, first run only; not in the throughput"
        rows.append(("compiling", f"{summary['compile_s']:.1f} s ({what})"))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


def _score_rows(summary: dict) -> list[tuple[str, str]]:
    """The console's lines on the heading against the references and the walked direction it has."""
    names = {"truth": "heading vs truth", "os": "heading vs phone's own"}
    rows = []
    errors = summary.get("heading_error", {})
    for name in names:
        e = errors.get(name)
        if e and e["n_epochs"]:
            rows.append((names[name],
                         f"median {e['median_deg']:.1f}°, p90 {e['p90_deg']:.1f}°, "
                         f"> 45° {100 * e['share_over_45']:.1f} % of {e['n_epochs']} rows"))
    w = summary.get("walked_direction")
    if w and w["n_segments"]:
        within = w["within_2sigma_share"]
        rows.append(("heading vs walked", f"{w['n_segments']} segments: median {w['median_deg']:.1f}°, mean "
                     f"{w['mean_deg']:.1f}°, > 45° {w['n_over_45']}, within 2σ "
                     + (f"{100 * within:.0f} %" if within is not None else "-")
                     + f", > 45° with σ ≤ 20° {w['n_over_45_sigma_le_20']}"))
    elif w:
        rows.append(("heading vs walked", "no segment (waypoints ≥ 4 m and 3 s apart)"))
    return rows


def _latency_line(summary: dict) -> str:
    """The summary table's line on the magnetometer's latency: given, estimated and applied, or not
    determined ("" when none was given or asked for)."""
    est = summary.get("mag_latency")
    used = summary.get("mag_time_offset_s") or 0.0
    if est is None:
        return f"{1000 * used:.1f} ms given: the magnetometer's stamps moved back by it" if used else ""
    if est["applied"]:
        return (f"{1000 * used:.1f} ms (± {1000 * est['std_s']:.1f}) estimated from the first "
                f"{est['span_s']:.0f} s and applied")
    if est["determined"]:  # an IMU later than the magnetometer: not corrected (latency.applies)
        return (f"{1000 * est['seconds']:.1f} ms (± {1000 * est['std_s']:.1f}) estimated from the first "
                f"{est['span_s']:.0f} s: the IMU is the later stream, none applied")
    why = "too little turning" if est["seconds"] is None or est["std_s"] is None else (
        f"{1000 * est['seconds']:.1f} ± {1000 * est['std_s']:.1f} ms, explaining {100 * est['gain']:.0f} % "
        "of the field's turn residual")
    return f"not determined from the first {est['span_s']:.0f} s ({why}): none applied"


def _gaps_line(gaps: dict | None) -> str:
    """The summary table's line on the streams' gaps: per stream, how many and how long in all; a stream that
    starts late or ends early says what the rows lack there."""
    if not gaps or not gaps["n"]:
        return "none"
    parts = []
    for name, g in gaps["per_stream"].items():
        text = f"{name} {g['n']} ({g['total_s']:.1f} s)"
        for x in gaps["gaps"]:
            if x["stream"] != name or x["where"] == "inside":
                continue
            late = x["where"] == "start"
            text += (f", starts {x['duration_s']:.1f} s after the others: " if late else
                     f", ends {x['duration_s']:.1f} s before the others: ")
            text += f"{_GAP_COST.get(name, 'without it')} {'before' if late else 'after'} "
            text += f"{x['t_to'] if late else x['t_from']:.1f} s"
        parts.append(text)
    return "; ".join(parts)


#: What the output lacks while a stream has no samples (the console's ``stream gaps``).
_GAP_COST = {"gyro": "no output rows", "accel": "the tilt on the gyroscope alone",
             "mag": "the heading on the gyroscope alone"}


def _prior_line(summary: dict) -> str:
    """The summary table's line on what the run started from: the phone's own estimates, the device store."""
    p = summary.get("prior")
    store = summary.get("device_store")
    parts = []
    if p is not None:
        what = [w for w, k in (("hard iron", "offset_uT"), ("gyro bias", "gyro_bias_rad_s")) if p.get(k)]
        stored = "store" in p.get("source", "") and p.get("age_s")
        age = f", {p['age_s'] / 3600:.1f} h old" if stored else ""
        parts.append(f"{' and '.join(what)} from the {p['source'].replace('+', ' and the ')}{age}")
    if store is not None:
        saved = "saved" if store["saved"] else "not saved"
        parts.append(f"device store {saved} ({store['file'] or 'the recording names no device'})")
    return "; ".join(parts) or "none"
