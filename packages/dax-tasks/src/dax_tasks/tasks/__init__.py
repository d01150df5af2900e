"""The nine benchmark tasks, each an :class:`dax_tasks.core.Env` subclass with its scene and
default :class:`dax_tasks.core.TaskSpec`s: the pour tasks (:mod:`.pour`), Push-Rope
(:mod:`.push_rope`), Whip-Rope (:mod:`.whip_rope`) and the five cloth tasks (:mod:`.cloth`).
Build them by name with :func:`dax_tasks.make`."""
