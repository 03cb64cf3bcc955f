"""jaxnrsfm: robust structure and motion factorization of nonrigid objects, in JAX.

The flow is tracks -> factorization -> metric upgrade -> Euclidean reconstruction ->
metrics; see ``README.md``.
"""

from .factorize import Factorization as Factorization, factorize as factorize
from .metrics import (
    align_shapes as align_shapes,
    e3d as e3d,
    entry_errors as entry_errors,
    mean_reprojection_error as mean_reprojection_error,
    outlier_precision_recall as outlier_precision_recall,
    rms_error as rms_error,
    statistical_floor as statistical_floor,
)
from .reconstruct import (
    Reconstruction as Reconstruction,
    reconstruct as reconstruct,
    reconstruct_prepared as reconstruct_prepared,
)
from .status import Status as Status
from .synthetic import (
    SyntheticSequence as SyntheticSequence,
    bregler_sequence as bregler_sequence,
    deformable_cube as deformable_cube,
    drop_entries as drop_entries,
    inject_outliers as inject_outliers,
)
from .tracks import from_frames as from_frames, prepare_tracks as prepare_tracks, to_frames as to_frames
from .upgrade import Euclidean as Euclidean, metric_upgrade as metric_upgrade

__version__ = "0.1.0"
