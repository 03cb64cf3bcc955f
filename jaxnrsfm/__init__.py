"""jaxnrsfm: robust structure and motion factorization of nonrigid objects, in JAX.

The flow is tracks -> factorization -> metric upgrade -> Euclidean reconstruction ->
metrics; see ``README.md``.
"""

from .batch import reconstruct_batch as reconstruct_batch
from .choose import choose_k as choose_k
from .factorize import Factorization as Factorization
from .factorize import factorize as factorize
from .metrics import (
    align_shapes as align_shapes,
)
from .metrics import (
    e3d as e3d,
)
from .metrics import (
    entry_errors as entry_errors,
)
from .metrics import (
    mean_reprojection_error as mean_reprojection_error,
)
from .metrics import (
    outlier_precision_recall as outlier_precision_recall,
)
from .metrics import (
    rms_error as rms_error,
)
from .metrics import (
    statistical_floor as statistical_floor,
)
from .pipeline import (
    Reconstruction as Reconstruction,
)
from .pipeline import (
    reconstruct as reconstruct,
)
from .pipeline import (
    reconstruct_prepared as reconstruct_prepared,
)
from .refine import nuclear_shapes as nuclear_shapes
from .stages import L1 as L1
from .stages import Direct as Direct
from .stages import HighRankRotations as HighRankRotations
from .stages import Huber as Huber
from .stages import Huynh as Huynh
from .stages import KeKanade as KeKanade
from .stages import MaskedALS as MaskedALS
from .stages import NuclearShapes as NuclearShapes
from .stages import Oracle as Oracle
from .stages import OutlierStrategy as OutlierStrategy
from .stages import RotationRecovery as RotationRecovery
from .stages import ShapeStep as ShapeStep
from .stages import TraceNormRotations as TraceNormRotations
from .stages import UpgradeRotations as UpgradeRotations
from .stages import UpgradeShapes as UpgradeShapes
from .stages import Wang as Wang
from .status import Status as Status
from .synthetic import (
    SyntheticSequence as SyntheticSequence,
)
from .synthetic import (
    articulated_sequence as articulated_sequence,
)
from .synthetic import (
    bregler_sequence as bregler_sequence,
)
from .synthetic import (
    deformable_cube as deformable_cube,
)
from .synthetic import (
    drop_entries as drop_entries,
)
from .synthetic import (
    inject_outliers as inject_outliers,
)
from .tracks import from_frames as from_frames
from .tracks import prepare_tracks as prepare_tracks
from .tracks import to_frames as to_frames
from .upgrade import Euclidean as Euclidean
from .upgrade import metric_upgrade as metric_upgrade

__version__ = "0.1.0"
