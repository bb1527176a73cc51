"""The deployment monitor: has the system left the data?

:class:`DeploymentMonitor` scores each transition with its detectors (:class:`DynamicsEnsemble`,
:class:`NearestStateDistance`, the TS-IDM's terms) and raises a windowed alarm, as a TorchRL ``Transform``;
:func:`make_monitor` and :class:`MonitorFit` fit the run's monitor to its training data, inline or in a process
of its own beside training; :func:`monitor_record` is what an evaluation records of it along its episodes.
"""
from torchrl_tels.envs.monitor import DeploymentMonitor
from torchrl_tels.modules.detectors import DynamicsEnsemble, fit_ensembles, NearestStateDistance
from torchrl_tels.monitor.episodes import monitor_record
from torchrl_tels.monitor.fit import check_monitor_data, make_monitor, monitor_data, monitor_in_background, MonitorFit

__all__ = [
    "DeploymentMonitor",
    "DynamicsEnsemble",
    "MonitorFit",
    "NearestStateDistance",
    "check_monitor_data",
    "fit_ensembles",
    "make_monitor",
    "monitor_data",
    "monitor_in_background",
    "monitor_record",
]
