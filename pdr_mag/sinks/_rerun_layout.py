"""The rerun sink's look: series styles, state colours and the default blueprint (:func:`drift_blueprint`).

The blueprint answers "when did the heading drift, and why" on one screen, over the whole recording:

left, on one time axis (every view shows the recording's whole time span, not a window round the cursor)
    heading (ours, truth, gyro only, the phone's own); the heading error against the truth with the
    filter's ±σ and ±2σ around zero, so the error reads against the uncertainty the filter claims; the
    interference detectors with a band (field strength and dip angle, with their bands: each registered
    detector's plot, :data:`pdr_mag.fusion.detectors.PLOTS`, ``main``); the state lanes — drift episodes,
    interference, calibration state, magnetometer use (share of each second), rotation episodes of the online
    calibrator.  The drift episodes, the interference flag and the seconds without the magnetometer are also
    drawn as strips along the top and bottom of the error plot, where they share the error's time axis exactly
    (the lanes' axis starts a little left of the plots', which reserve room for their y labels).
right
    the magnetometer cloud (raw and calibrated, accumulated up to the cursor) with the latest fit only; tabs
    for the detector score, the other detectors (strength variance, gyro consistency), the magnetometer's
    share, σ, coverage and one plot per input sensor; the events.

The y ranges are fitted to the part of the recording after the first magnetometer correction (before it the
heading is arbitrary and σ is 180°), from :class:`PlotRanges` gathered by the sink; legends are hidden and
the view titles name the series and their colours instead, so nothing covers the curves.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import rerun as rr
import rerun.blueprint as rrb

from pdr_mag.fusion.detectors import BANDS, PLOTS

# colours (RGB): one per meaning, shared by the lines and the titles that name them
BLUE = (31, 119, 180)
ORANGE = (255, 127, 14)
GREEN = (44, 160, 44)
RED = (214, 39, 40)
PURPLE = (148, 103, 189)
BLACK = (40, 40, 40)
GREY = (170, 170, 170)
LIGHT_GREEN = (160, 215, 160)
SIGMA1 = (130, 130, 130)
SIGMA2 = (195, 195, 195)
CYAN = (23, 190, 207)
OLIVE = (188, 189, 34)
BROWN = (140, 86, 75)

#: the colours the detectors' plots name (:class:`pdr_mag.fusion.detectors._unit.Plot`)
COLOURS = {"blue": BLUE, "orange": ORANGE, "green": GREEN, "red": RED, "purple": PURPLE, "cyan": CYAN,
           "olive": OLIVE, "brown": BROWN}  # fmt: skip

DRIFT = {"error": (200, 0, 0), "sigma": (240, 120, 0), "no_reference": (250, 190, 40)}
#: entity → (legend name, colour, drawn as points, line width or marker size in UI points).
SERIES = {
    "heading/ours": ("ours", BLUE, True, 1.5),
    "heading/unreferenced": ("ours before the first magnetometer correction (arbitrary)", GREY, True, 1.5),
    "heading/truth": ("truth", BLACK, True, 1.5),
    "heading/gyro_only": ("gyro only", ORANGE, True, 1.5),
    "heading/os": ("phone (OS)", GREEN, True, 1.5),
    "heading_error/ours": ("ours − truth", BLUE, False, 2.5),
    "heading_error/gyro_only": ("gyro only − truth", ORANGE, False, 1.5),
    "heading_error/os": ("phone − truth", LIGHT_GREEN, True, 1.0),
    "heading_error/plus_1sigma": ("+σ", SIGMA1, False, 1.0),
    "heading_error/minus_1sigma": ("−σ", SIGMA1, False, 1.0),
    "heading_error/plus_2sigma": ("+2σ", SIGMA2, False, 1.0),
    "heading_error/minus_2sigma": ("−2σ", SIGMA2, False, 1.0),
    "heading_error/strip_drift_error": ("drift episode: error", DRIFT["error"], False, 6.0),
    "heading_error/strip_drift_sigma": ("drift episode: σ", DRIFT["sigma"], False, 6.0),
    "heading_error/strip_drift_no_reference": ("drift episode: no ref.", DRIFT["no_reference"], False, 6.0),
    "heading_error/strip_interference": ("interference flagged", RED, False, 6.0),
    "heading_error/strip_no_magnetometer": ("magnetometer not used", ORANGE, False, 6.0),
    "heading_std/ours": ("1σ", BLUE, False, 1.5),
    **{f"{p.group}/{p.leaf}": (p.label, COLOURS[p.colour], False, 1.5) for p in PLOTS.values()},
    **{
        f"{PLOTS[name].group}/{leaf}": (label, colour, False, 1.5)
        for name in BANDS
        for leaf, label, colour in (("reference", "reference", BLACK), ("lower", "band lower", RED),
                                    ("upper", "band upper", RED))
    },  # fmt: skip
    "detector/score": ("score", BROWN, False, 1.5),
    "detector/threshold": ("threshold", RED, False, 1.5),
    "mag_use/share": ("share of the second", GREEN, False, 1.5),
    "coverage/online": ("online buffer", CYAN, False, 1.5),
    "coverage/calibration": ("calibration", OLIVE, True, 1.5),
}
#: entity → {state: colour}; clean and normal states are quiet (light), trouble is loud (saturated).
STATES = {
    "state/drift": DRIFT,
    "state/interference": {"clean": (232, 232, 232), "interference": (214, 39, 40)},
    "state/magnetometer": {"used": (214, 236, 214), "partly": (250, 210, 140), "not used": (240, 120, 0)},
    "state/rotation": {"rotating": (150, 190, 230)},
    "state/mag_calibration": {
        "none": (250, 200, 200),
        "offset": (214, 228, 242),
        "ellipsoid": (200, 230, 200),
        "recalibrating": (250, 190, 40),
    },
}
#: labels shown in the lanes.
STATE_LABELS = {"error": "error", "sigma": "σ", "no_reference": "no reference"}
#: point radius of the 3-D clouds, in UI points (constant on screen whatever the field strength).
CLOUD_RADIUS_UI = 2.0
RAW_COLOR, CAL_COLOR, REJECTED_COLOR = (150, 150, 150), BLUE, RED
RAW_FIT_COLOR, SPHERE_COLOR = ORANGE, BLUE


@dataclass
class PlotRanges:
    """What the blueprint's axes are fitted to (None: let the viewer choose).

    Attributes
    ----------
    t : (float, float) or None
        The recording's time span, s.
    error : float or None
        Half-height of the heading error plot, deg.
    bands : dict
        y ranges of the plots of the detectors with a band (their plot group → (low, high)): field
        strength (µT) and dip (deg).
    truth : bool
        Whether a truth was drawn (the error plot's title says what it holds).
    """

    t: tuple[float, float] | None = None
    error: float | None = None
    bands: dict = field(default_factory=dict)
    truth: bool = True


def drift_blueprint(ranges: PlotRanges | None = None):
    """The default layout (module docstring), with axes fitted to ``ranges``."""
    r = ranges or PlotRanges()

    def time_axis():
        if r.t is None:
            return None
        lo, hi = r.t
        pad = max(0.01 * (hi - lo), 0.5)
        span = rr.TimeRange(
            start=rrb.TimeRangeBoundary.absolute(seconds=lo - pad),
            end=rrb.TimeRangeBoundary.absolute(seconds=hi + pad),
        )
        return rrb.TimeAxis(view_range=span)

    def plot(origin, name, y=None, contents="$origin/**"):
        return rrb.TimeSeriesView(
            origin=origin,
            contents=contents,
            name=name,
            axis_x=time_axis(),
            axis_y=None if y is None else rrb.ScalarAxis(range=y),
            plot_legend=rrb.PlotLegend(visible=False),
        )

    err = None if r.error is None else (-r.error, r.error)
    bars = "bars: drift episodes (top), interference, no magnetometer (bottom)"
    error_title = (
        f"Heading error vs truth, deg: ours (blue) in ±σ, ±2σ (grey); {bars}"
        if r.truth
        else f"Heading uncertainty (no truth here), deg: ±σ, ±2σ (grey); {bars}"
    )
    lanes = rrb.StateTimelineView(
        origin="/state",
        name="Drift episodes · interference · calibration · magnetometer use · rotation episodes",
        time_view=time_axis(),
    )
    heading_title = "Heading, deg: ours (blue), truth (black), gyro only (orange), phone (green)"
    main = [
        plot(f"/{p.group}", f"{p.title}: {p.label} ({p.colour}), reference (black), detector band (red)",
             r.bands.get(p.group))
        for p in PLOTS.values()
        if p.main
    ]  # fmt: skip
    tabs = [plot(f"/{p.group}", f"{p.title}: {p.label} ({p.colour})") for p in PLOTS.values() if not p.main]
    left = rrb.Vertical(
        plot("/heading", heading_title, (0.0, 360.0)),
        plot("/heading_error", error_title, err),
        *main,
        lanes,
        row_shares=[1.1, 2.5, *[1.9] * len(main), 2.6],
    )
    cloud_range = rrb.VisibleTimeRanges(
        [
            rrb.VisibleTimeRange(
                "time", start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
            )
        ]
    )
    right = rrb.Vertical(
        rrb.Spatial3DView(
            origin="/mag",
            name="Magnetometer, µT: raw (grey) + latest fit (orange); calibrated (blue) on the field sphere",
            overrides={"/mag/raw": cloud_range, "/mag/calibrated": cloud_range},
        ),
        rrb.Tabs(
            plot("/detector", "Interference score (≥ 1 flags)"),
            *tabs,
            plot("/mag_use", "Magnetometer use, share of each second", (0.0, 1.05)),
            plot("/heading_std", "Heading σ, deg"),
            plot("/estimates/gyro_bias", "Gyro bias the filter estimates, °/s (x red, y green, z blue)"),
            plot("/estimates/offset_error",
                 "Calibration offset error the filter found, µT (x red, y green, z blue)"),
            plot("/coverage", "Coverage", (0.0, 1.05)),
            plot("/inputs/accel", "Accelerometer, m/s² (x red, y green, z blue)"),
            plot("/inputs/gyro", "Gyroscope, rad/s (x red, y green, z blue)"),
            plot("/inputs/mag", "Magnetometer raw, µT (x red, y green, z blue)"),
        ),
        rrb.TextLogView(origin="/events", name="Events (click one to jump there)"),
        row_shares=[3.0, 2.0, 2.0],
    )
    return rrb.Blueprint(
        rrb.Horizontal(left, right, column_shares=[3.0, 2.0]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )
