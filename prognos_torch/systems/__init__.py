"""Simulated systems of the four studies, each exposed as the state-space model a filter uses.

Each system has one per-sample dynamics function (pure torch, vmap-friendly, also accepting
leading batch dimensions), a ``*_model`` factory returning the :class:`StateSpaceModel` with the
true parameter / fault profile, a joint model with the drifting parameter or faults as
random-walk states where the paper uses one, and a ``simulate_*`` function that runs that very
model (see :func:`simulate_model`) and returns a :class:`SimulationResult` with time leading:
``x`` ``(T+1, runs, n)``, ``y`` ``(T, runs, m)``, ``theta`` ``(T+1, runs, d)``.

* :mod:`.cstr` - CSTR with feed-concentration drift (paper 003 Eq. 50-51, Table II).
* :mod:`.three_tank` - DTS200 with ``az2`` drift (paper 000 Eq. 57-63).
* :mod:`.lorenz` - Lorenz system and the Lorenz(x) series (paper 003 Eq. 47).
* :mod:`.high_speed_train` - five-car train with actuator/coupler/sensor faults (paper 004).
* :mod:`.battery` - equivalent-circuit battery with end of discharge (progpy's BatteryCircuit).
* :mod:`.run_to_failure` - synthetic run-to-failure indicators from degradation processes outside
  the trend models of :func:`~prognos_torch.workflow.prognose` (shocks, Paris-law crack growth,
  two-phase exponential, exponential with a transient hump).

Shared pieces: :mod:`.simulation` (the loop, :class:`SimulationResult`, parameter paths),
:mod:`.noise_streams` (per-run random streams), :mod:`.integrators` (RK4, Euler). Argument
checks live in :mod:`prognos_torch.core.validation`; min-max scaling in
:mod:`prognos_torch.datasets.windows`.

Equations, parameter sources and the readings chosen where a paper is ambiguous:
``docs/systems.md``.
"""

from .battery import (
    BatteryCircuitParams,
    battery_circuit_model,
    battery_eod_event,
    simulate_battery,
)
from .cstr import (
    CSTRParams,
    cstr_feed_drift,
    cstr_joint_model,
    cstr_model,
    cstr_rhs,
    cstr_steady_state,
    cstr_step,
    simulate_cstr,
)
from .high_speed_train import (
    HST_FAULT_NAMES,
    HSTParams,
    hst_actuator_fault,
    hst_coupler_fault,
    hst_cruise_speed,
    hst_estimation_errors,
    hst_fault_model,
    hst_measure,
    hst_measurement_variance,
    hst_model,
    hst_noise_variances,
    hst_nominal_fault_model,
    hst_process_variance,
    hst_rhs,
    hst_sensor_fault,
    hst_state_names,
    hst_step,
    simulate_hst,
    simulate_hst_runs,
)
from .integrators import euler_step, rk4_step
from .lorenz import (
    LorenzParams,
    lorenz_model,
    lorenz_rhs,
    lorenz_series,
    lorenz_step,
    simulate_lorenz,
)
from .noise_streams import draw_run_noise
from .run_to_failure import (
    RUN_TO_FAILURE_FAMILIES,
    RunToFailure,
    run_to_failure_set,
    simulate_run_to_failure,
)
from .simulation import SimulationResult, simulate_model
from .three_tank import (
    ThreeTankParams,
    az2_drift,
    simulate_three_tank,
    three_tank_equilibrium,
    three_tank_joint_model,
    three_tank_model,
    three_tank_rhs,
    three_tank_step,
)

__all__ = [
    "SimulationResult",
    "rk4_step",
    "euler_step",
    "simulate_model",
    "draw_run_noise",
    "BatteryCircuitParams",
    "battery_circuit_model",
    "battery_eod_event",
    "simulate_battery",
    "CSTRParams",
    "cstr_rhs",
    "cstr_step",
    "cstr_feed_drift",
    "cstr_steady_state",
    "cstr_model",
    "cstr_joint_model",
    "simulate_cstr",
    "ThreeTankParams",
    "three_tank_rhs",
    "three_tank_step",
    "az2_drift",
    "three_tank_equilibrium",
    "three_tank_model",
    "three_tank_joint_model",
    "simulate_three_tank",
    "LorenzParams",
    "lorenz_rhs",
    "lorenz_step",
    "lorenz_model",
    "simulate_lorenz",
    "lorenz_series",
    "HSTParams",
    "HST_FAULT_NAMES",
    "hst_state_names",
    "hst_rhs",
    "hst_step",
    "hst_measure",
    "hst_cruise_speed",
    "hst_actuator_fault",
    "hst_coupler_fault",
    "hst_sensor_fault",
    "hst_process_variance",
    "hst_measurement_variance",
    "hst_noise_variances",
    "hst_estimation_errors",
    "hst_model",
    "hst_fault_model",
    "hst_nominal_fault_model",
    "simulate_hst",
    "simulate_hst_runs",
    "RUN_TO_FAILURE_FAMILIES",
    "RunToFailure",
    "simulate_run_to_failure",
    "run_to_failure_set",
]
