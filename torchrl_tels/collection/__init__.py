"""Making offline data: a Minari writer for any policy, the PointMaze waypoint controller and
the point-mass behaviour policy; the DAPG Adroit experts."""
from torchrl_tels.collection.dapg import load_dapg_expert
from torchrl_tels.collection.minari_writer import collect_minari_dataset
from torchrl_tels.collection.point_mass import make_point_mass_dataset
from torchrl_tels.collection.pointmaze import collect_pointmaze_dataset, WaypointController

__all__ = ["WaypointController", "collect_minari_dataset", "load_dapg_expert", "collect_pointmaze_dataset", "make_point_mass_dataset"]
