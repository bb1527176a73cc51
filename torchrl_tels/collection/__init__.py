"""Making offline data: a Minari writer for any policy, the PointMaze waypoint controller and
the point-mass behaviour policy."""
from torchrl_tels.collection.minari_writer import collect_minari_dataset
from torchrl_tels.collection.point_mass import make_point_mass_dataset
from torchrl_tels.collection.pointmaze import collect_pointmaze_dataset, WaypointController

__all__ = ["WaypointController", "collect_minari_dataset", "collect_pointmaze_dataset", "make_point_mass_dataset"]
