"""Simulation vs measured: find where the sensor model and a recording disagree, name the missing effect.

``diagnose(...)`` estimates the orientation from the recording's gyroscope and accelerometer
(:mod:`.orientation`; ``truth`` only with ``use_truth=True``), fits the baseline model (hard_iron + noise)
along it (:mod:`.fit`), simulates the magnetometer with :mod:`pdr_mag.sim.sensor_model` (:mod:`.predict`) and
adds candidate effects one at a time by a penalised likelihood (:mod:`.select`) until nothing significant
is left.  Then it says, for every candidate, what the recording's motion can reveal of it (:mod:`.identify`:
the Fisher information of its parameters against the final model — a texting walk turns about one axis and
leaves directions that the hard iron or the heading reference take) — nothing is left out silently.
:mod:`.gyro` finds the ``gyro_bias`` candidate's start value and replays the orientation with it;
:mod:`.diagnosis` holds the settings, the records of a diagnosis and the estimates in the JSON's units;
:mod:`.report` writes the human report.

Heading reference: the gyro + accelerometer orientation fixes tilt but not heading, so its world frame has
an arbitrary yaw; the predicted field ``m_d(t) = S⁻¹ Mᵀ R_dw(t) B_w + b`` fits ``B_w`` (3 components, in
that frame) together with ``b`` — the heading reference comes from the fit itself.  ``truth.csv`` is used
only with ``use_truth=True`` (evaluation mode), and then the same ``B_w`` is still fitted.
"""

from pdr_mag.modelcheck.diagnosis import GAP_METRIC, Candidate, DiagnoseSettings, Diagnosis
from pdr_mag.modelcheck.fit import BASELINE, CANDIDATES
from pdr_mag.modelcheck.null import NullSettings
from pdr_mag.modelcheck.orientation import OrientationSettings, estimate_orientation
from pdr_mag.modelcheck.select import diagnose

__all__ = [
    "BASELINE",
    "CANDIDATES",
    "GAP_METRIC",
    "NullSettings",
    "Candidate",
    "DiagnoseSettings",
    "Diagnosis",
    "OrientationSettings",
    "diagnose",
    "estimate_orientation",
]
