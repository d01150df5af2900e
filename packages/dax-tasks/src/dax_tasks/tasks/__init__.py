"""The nine benchmark tasks, each an :class:`dax_tasks.core.Env` subclass with its scene and
default :class:`dax_tasks.core.TaskSpec`\\ s: the pour tasks (:mod:`.pour`), Push-Rope
(:mod:`.push_rope`), Whip-Rope (:mod:`.whip_rope`) and the five cloth tasks (:mod:`.cloth`).

Importing this package registers them (:func:`dax_tasks.core.registry.register`) by
``"module:attribute"`` strings, so no task module is imported until a task is built with
:func:`dax_tasks.make`.
"""

from ..core.registry import register
from ..core.spec import ONLY_FOR

#: The nine benchmark tasks, in the literature's order.
TASKS = (
    "pour_water", "pour_soup", "push_rope", "whip_rope", "fold_cloth1", "fold_cloth3",
    "fold_tshirt", "unfold_cloth1", "unfold_cloth3",
)

# name -> (module, Env subclass, default spec; the reference spec is <spec>_REFERENCE)
_BENCHMARK = {
    "pour_water": ("pour", "Pour", "POUR_WATER"),
    "pour_soup": ("pour", "Pour", "POUR_SOUP"),
    "push_rope": ("push_rope", "PushRope", "PUSH_ROPE"),
    "whip_rope": ("whip_rope", "WhipRope", "WHIP_ROPE"),
    "fold_cloth1": ("cloth", "ClothTask", "FOLD_CLOTH1"),
    "fold_cloth3": ("cloth", "ClothTask", "FOLD_CLOTH3"),
    "fold_tshirt": ("cloth", "ClothTask", "FOLD_TSHIRT"),
    "unfold_cloth1": ("cloth", "ClothTask", "UNFOLD_CLOTH1"),
    "unfold_cloth3": ("cloth", "ClothTask", "UNFOLD_CLOTH3"),
}


def _register_benchmark() -> None:
    for name in TASKS:
        module, cls, spec = _BENCHMARK[name]
        where = f"{__name__}.{module}"
        register(name, f"{where}:{cls}", f"{where}:{spec}",
                 reference=f"{where}:{spec}_REFERENCE")


_register_benchmark()

# The files only some of the nine reach, by the modules defining their scenes (what a
# task's fingerprint leaves out; tested by profiling one task per scene module)
ONLY_FOR.update({
    "dax_physics/cloth/": (f"{__name__}._cloth",),
    "dax_tasks/tasks/_cloth.py": (f"{__name__}._cloth",),
    "dax_tasks/tasks/cloth.py": (f"{__name__}._cloth",),
    "dax_physics/mpm/": (f"{__name__}.pour", f"{__name__}.push_rope", f"{__name__}.whip_rope"),
    "dax_tasks/tasks/pour.py": (f"{__name__}.pour",),
    "dax_tasks/tasks/_rope.py": (f"{__name__}.push_rope", f"{__name__}.whip_rope"),
    "dax_tasks/tasks/push_rope.py": (f"{__name__}.push_rope",),
    "dax_tasks/tasks/whip_rope.py": (f"{__name__}.whip_rope",),
})

__all__ = ["TASKS"]
