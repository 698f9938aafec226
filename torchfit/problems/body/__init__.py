"""The rigged body: Young's modulus of a tetrahedralised character fitted to its animation.

:class:`RiggedBody` (``problem=animation``: the user's own animation folder, USD stage or
glTF file) and :class:`Arm3D` (``problem=arm3d``: the procedural arm, written as such an
animation first) share everything: the tetrahedral mesh (:mod:`.setup`), the parameter grid
along the body's principal axes (:mod:`.grid`, :mod:`.frame`), validation frames
(:mod:`.held_out`), bounds on the modulus (:mod:`.bounds`) and the collaborators the body
owns: its energy (:mod:`.energy`), its simulation, the equilibrium per frame with repeated
poses simulated once (:mod:`.poses`, :mod:`.repeated_poses`) or the integration through
time (:mod:`.dynamic`), its observation (:mod:`.observation`), its report (:mod:`.reporter`
on :mod:`.report`'s functions and :mod:`.motion`), the model comparison
(:mod:`.model_comparison`); a run's own mesh (:mod:`.run_mesh`), a painted start
(:mod:`.init_field`).
"""
from .arm3d import Arm3D, Arm3DConfig
from .config import RiggedBodyConfig
from .problem import RiggedBody
from .run_mesh import RUN_MESH_FILE, fitted_mesh, keep_mesh, read_run_mesh, resumed_mesh

__all__ = ["Arm3D", "Arm3DConfig", "RUN_MESH_FILE", "RiggedBody", "RiggedBodyConfig",
           "fitted_mesh", "keep_mesh", "read_run_mesh", "resumed_mesh"]
