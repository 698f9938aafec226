"""The rigged body: Young's modulus of a tetrahedralised character fitted to its animation.

:class:`RiggedBody` (``problem=animation``: the user's own animation folder, USD stage or
glTF file) and :class:`Arm3D` (``problem=arm3d``: the procedural arm, written as such an
animation first) share everything: the tetrahedral mesh (:mod:`.setup`), the parameter grid
along the body's principal axes (:mod:`.grid`, :mod:`.frame`), repeated poses simulated
once (:mod:`.repeated_poses`), validation frames (:mod:`.held_out`), bounds on the modulus
(:mod:`.bounds`), the model comparison (:mod:`.model_comparison`) and what the run reports
(:mod:`.report`, :mod:`.motion`).
"""
from .arm3d import Arm3D, Arm3DConfig
from .config import RiggedBodyConfig
from .problem import RiggedBody

__all__ = ["Arm3D", "Arm3DConfig", "RiggedBody", "RiggedBodyConfig"]
