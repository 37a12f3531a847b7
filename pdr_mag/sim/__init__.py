"""Phone-sensor simulator: scenario trajectories through :mod:`pdr_mag.sim.sensor_model`.

>>> from pdr_mag.sim import simulate
>>> res = simulate("mixed", seed=1, effects={"time_offset": 0.04})
>>> t_mag, mag_d = res.mag           # raw magnetometer, µT, device frame
>>> res.model                        # the exact SensorModel used (effects and values)
>>> res.trajectory.orientation(t)    # truth at any time (analytic)

Modules: :mod:`~pdr_mag.sim.kinematics` (rotation chain, exact body rate), :mod:`~pdr_mag.sim.modes`
(texting, swing, pocket, figure8, still, running in the hand and in a pocket),
:mod:`~pdr_mag.sim.trajectory` (modes blended along a walked path), :mod:`~pdr_mag.sim.scenarios` (named
scenarios, default effects, steel layouts), :mod:`~pdr_mag.sim.building` (a building's own weak field),
:mod:`~pdr_mag.sim.phones` (named phones: hardware and own magnetisation), :mod:`~pdr_mag.sim.sampling`
(jittered clocks, drops), :mod:`~pdr_mag.sim.simulator` (``simulate``).
"""

from pdr_mag.sim.building import BuildingField, FieldSum
from pdr_mag.sim.phones import PHONES, Phone
from pdr_mag.sim.scenarios import DEFAULT_EFFECTS, SCENARIOS, layout_dipoles
from pdr_mag.sim.simulator import DEFAULT_SITE, SimResult, resolve_effects, simulate
from pdr_mag.sim.trajectory import Trajectory

__all__ = [
    "BuildingField",
    "DEFAULT_EFFECTS",
    "DEFAULT_SITE",
    "FieldSum",
    "PHONES",
    "SCENARIOS",
    "Phone",
    "SimResult",
    "Trajectory",
    "layout_dipoles",
    "resolve_effects",
    "simulate",
]
