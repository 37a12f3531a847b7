"""Simulation vs measured: find where the sensor model and a recording disagree, name the missing effect.

``diagnose(...)`` estimates the orientation from the recording's gyroscope and accelerometer
(:mod:`.orientation`; ``truth`` only with ``use_truth=True``), fits the baseline model (hard_iron + noise)
along it (:mod:`.fit`), simulates the magnetometer with :mod:`pdr_mag.sensor_model` (:mod:`.predict`) and
adds candidate effects one at a time by a penalised likelihood (:mod:`.select`) until nothing significant
is left.  :mod:`.report` writes the human report.
"""

from pdr_mag.modelcheck.fit import BASELINE, CANDIDATES
from pdr_mag.modelcheck.orientation import OrientationSettings, estimate_orientation
from pdr_mag.modelcheck.select import GAP_METRIC, Candidate, DiagnoseSettings, Diagnosis, diagnose

__all__ = [
    "BASELINE",
    "CANDIDATES",
    "GAP_METRIC",
    "Candidate",
    "DiagnoseSettings",
    "Diagnosis",
    "OrientationSettings",
    "diagnose",
    "estimate_orientation",
]
