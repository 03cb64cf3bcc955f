"""The stages of a reconstruction, as ``eqx.Module``s to compose and extend:

tracks -> `MaskedALS` (missing data) + `OutlierStrategy` (the low-rank fit)
-> metric upgrade (where a stage reads it: ``needs_upgrade``) -> `RotationRecovery` -> `ShapeStep`
-> reconstruction.

Each abstract base documents its contract; `jaxnrsfm.reconstruct` takes instances.
"""

from .outliers import L1 as L1
from .outliers import STRATEGIES as STRATEGIES
from .outliers import Direct as Direct
from .outliers import Huber as Huber
from .outliers import Huynh as Huynh
from .outliers import KeKanade as KeKanade
from .outliers import Oracle as Oracle
from .outliers import OutlierStrategy as OutlierStrategy
from .outliers import Wang as Wang
from .rotations import ROTATIONS as ROTATIONS
from .rotations import HighRankRotations as HighRankRotations
from .rotations import RotationRecovery as RotationRecovery
from .rotations import TraceNormRotations as TraceNormRotations
from .rotations import UpgradeRotations as UpgradeRotations
from .shapes import SHAPES as SHAPES
from .shapes import NuclearShapes as NuclearShapes
from .shapes import ShapeStep as ShapeStep
from .shapes import UpgradeShapes as UpgradeShapes
from .solver import MaskedALS as MaskedALS
