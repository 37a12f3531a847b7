"""Heading against the walked direction on every trace with surveyed waypoints, against the peers.

Traces: every recording under ``../shared/datasets`` that a reader opens and whose ``meta["waypoints"]`` give
segments (today the 40 shopping-mall traces of ``ms-indoor-location-2020``), in the order of their names
(their ids sort by recording time).  Segments and scoring: :mod:`replay.heading_scores`, the definitions of
``../shared/tools/walked-direction`` (consecutive waypoints ≥ 4 m and ≥ 3 s apart, the circular mean heading
over the middle half of the segment against the waypoints' bearing).  Peers: the per-segment errors of
``../shared/benchmarks/walked_peers.csv`` (the phone's own fusion; VQF and imufusion fed the OS-calibrated
field), compared on the same segments.

Runs of the product, each ``replay.run.replay`` as ``pdr-mag replay`` runs it:

``default``
    ``pdr-mag replay TRACE``: what the file itself carries may be used (the phone's own hard-iron and gyro
    estimates, :mod:`pdr_mag.calibration.prior`; its fused heading on the rows pdr_mag has none for,
    :mod:`pdr_mag.pipeline.phone_heading`).
``store``
    ``pdr-mag replay TRACE --device-store DIR --ignore-phone-calibration``: one device store for all the
    traces, replayed in time order, the phone's own estimates (and heading) not used — what a backend that
    keeps its devices' calibrations gets (the first trace starts cold).
``cold``
    ``--ignore-phone-calibration`` without a store: every trace starts with nothing known.
``os_field``
    ``pdr-mag replay`` of the trace as a logger that keeps only the OS-calibrated field would have written
    it (IPIN's logger, iOS's calibrated field): a copy without its ``TYPE_MAGNETIC_FIELD_UNCALIBRATED``
    lines (the floor's map beside it), so the product reads ``TYPE_MAGNETIC_FIELD`` — the very field the
    VQF and imufusion peers are fed — and knows neither the OS's bias nor when the OS changes it.

Figures per run: segments, median / mean |error|, segments beyond 20° / 45°, the share within 2σ (σ the
median ``heading_std_deg`` over the window) and the segments more than 45° off with σ ≤ 20°; the peers on the
same segments.

Usage::

    python benchmarks/walked.py [--runs default store cold os_field] [--write-results]
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import SHARED, write_section  # noqa: E402

from pdr_mag.calibration.prior import PriorSettings  # noqa: E402
from pdr_mag.calibration.store import DeviceStore  # noqa: E402
from pdr_mag.pipeline import PipelineSettings  # noqa: E402
from replay.formats import open_recording  # noqa: E402
from replay.heading_scores import pooled  # noqa: E402
from replay.run import replay  # noqa: E402

DATA = SHARED / "datasets"
PEERS = SHARED / "benchmarks" / "walked_peers.csv"
SECTION = "## Heading against the walked direction (issue 19)"
RUNS = ("default", "store", "cold", "os_field")


def traces() -> list[Path]:
    """The recordings under ``../shared/datasets`` with waypoints: the mall traces' path files."""
    return sorted(DATA.glob("ms-indoor-location-2020/**/path_data_files/*.txt"), key=lambda p: p.stem)


def peers() -> dict:
    """``{(trace, segment): {peer: error_deg}}`` from walked_peers.csv."""
    out = {}
    with PEERS.open() as fh:
        for row in csv.DictReader(fh):
            out[(row["trace"], int(row["segment"]))] = {
                k[:-4]: float(v) for k, v in row.items() if k.endswith("_err")
            }
    return out


def os_field_copy(trace: Path, tmp: Path) -> Path:
    """A copy of a mall trace without its raw magnetometer lines, under ``tmp`` at its path in the dataset
    (``<site>/<floor>/path_data_files/<id>.txt``), the floor's ``geojson_map.json`` beside it as there."""
    floor = tmp / trace.parent.parent.relative_to(DATA)
    (floor / "path_data_files").mkdir(parents=True, exist_ok=True)
    geo = trace.parent.parent / "geojson_map.json"
    if geo.is_file() and not (floor / geo.name).exists():
        (floor / geo.name).write_bytes(geo.read_bytes())
    out = floor / "path_data_files" / trace.name
    with trace.open(encoding="utf-8") as src, out.open("w", encoding="utf-8") as dst:
        dst.writelines(line for line in src if "\tTYPE_MAGNETIC_FIELD_UNCALIBRATED\t" not in line)
    return out


def run(kind: str, paths: list[Path], store_dir: Path) -> tuple[dict, float]:
    """Every trace replayed as ``kind``; ``{(trace, segment): (error, sigma)}`` and the seconds taken (the
    ``os_field`` copies made before the clock starts)."""
    use_phone = kind in ("default", "os_field")
    settings = PipelineSettings(prior=PriorSettings(use_phone=use_phone))
    store = DeviceStore(store_dir) if kind == "store" else None
    if kind == "os_field":
        paths = [os_field_copy(p, store_dir) for p in paths]
    out = {}
    t0 = time.perf_counter()
    for p in paths:
        summary = replay(open_recording(p), settings=settings, device_store=store, progress=False)
        walked = summary.get("walked_direction") or {}
        for i, seg in enumerate(walked.get("segments", [])):
            sigma = seg["sigma_deg"]
            out[(p.stem, i)] = (seg["error_deg"], float("nan") if sigma is None else sigma)
    return out, time.perf_counter() - t0


def table(results: dict, peer: dict) -> list[str]:
    keys = sorted(set(next(iter(results.values()))[0]))
    names = sorted({k for v in peer.values() for k in v})
    lines = ["| method | segments | median | mean | > 20° | > 45° | within 2σ | > 45° at σ ≤ 20° | time |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for kind, (res, secs) in results.items():
        f = pooled([res[k] for k in keys])
        w2 = f["within_2sigma_share"]
        w2 = "-" if w2 is None else f"{100 * w2:.0f} %"
        lines.append(f"| pdr_mag `{kind}` | {f['n_segments']} | **{f['median_deg']:.2f}** | "
                     f"**{f['mean_deg']:.2f}** | {f['n_over_20']} | {f['n_over_45']} | {w2} | "
                     f"{f['n_over_45_sigma_le_20']} | {secs:.0f} s |")
    for name in names:
        f = pooled([(peer[k][name], float("nan")) for k in keys if name in peer.get(k, {})])
        lines.append(f"| {name} | {f['n_segments']} | {f['median_deg']:.2f} | {f['mean_deg']:.2f} | "
                     f"{f['n_over_20']} | {f['n_over_45']} | - | - | |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", choices=RUNS, default=list(RUNS))
    ap.add_argument("--write-results", action="store_true")
    a = ap.parse_args()
    paths = traces()
    if not paths:
        sys.exit(f"no trace with waypoints under {DATA}")
    peer = peers()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in a.runs:
            results[kind] = run(kind, paths, Path(tmp) / kind)
            print(f"{kind}: {len(results[kind][0])} segments in {results[kind][1]:.0f} s", file=sys.stderr)
    lines = table(results, peer)
    print("\n".join(lines))
    if a.write_results:
        text = "\n".join([
            SECTION, "",
            f"`python benchmarks/walked.py --write-results` ({len(paths)} traces of "
            "`../shared/datasets/ms-indoor-location-2020`, in time order). |error| of the circular mean "
            "heading over the middle half of each segment between surveyed waypoints against its bearing, "
            "deg (`../shared/tools/walked-direction`'s scoring, `replay.heading_scores`); peers from "
            "`../shared/benchmarks/walked_peers.csv` on the same segments. Runs: `default` = `pdr-mag replay "
            "TRACE` (the phone's own estimates used as priors, its heading on the rows pdr_mag has none "
            "for); `store` = one device store for all traces, the phone's estimates not used; "
            "`cold` = nothing known at each start; `os_field` = each trace "
            "without its raw magnetometer lines, as a logger keeping only the OS-calibrated field writes it "
            "(the field the peers are fed).", "", *lines, ""])
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
