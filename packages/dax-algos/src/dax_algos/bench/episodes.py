"""Episodes as pictures: what a benchmark run records of each episode, and the pictures the
results page shows of it.

**Recording** (during the run; a few kB per row). Beside every results row the runner
writes ``episodes/<task>/<method>/seed<k>.npz`` (:func:`save_episode`, atomically; read
with ``allow_pickle=False``): the key the episode's start was drawn with (``reset_key``,
given to ``env.reset`` as it is), the executed actions ``(T, action_dim)`` in task units,
the final-step r_gt of that episode (``score``) and the task spec's fingerprint. A
planner's episode is the row's (its start ``fold_in(PRNGKey(k), 0)``); a learner's row is
the mean of its ``n_eval`` evaluation rollouts, of which the first is recorded (start
``split(fold_in(PRNGKey(k), 0), n_eval)[0]``, ``rollout = 0``, ``n_rollouts = n_eval``).

**Pictures** (after the timed work, :func:`episode_pictures`). For each (task, method) the
median-score seed (:func:`median_row`) is replayed from its actions with the env's pure
``reset`` / ``step`` (one jitted ``lax.scan`` per task), which gives its states, and drawn
with :func:`dax_tasks.viz.scene_frames`: a looping GIF and a filmstrip of key frames
beside the goal. The replayed final r_gt is compared with the recorded one; a difference
over :data:`MISMATCH` is flagged on the page. (The replay's program is not the runner's:
a learner's recorded rollout ran inside its vmapped evaluation, and another program
shape can round differently; a mismatching replay is tried once more under ``vmap`` over
a batch of one, which the page then names.) Pictures are named by the seed and a
hash of everything they depend on (the task's fingerprint, the start key, the actions,
the drawing settings), so drawing them again is skipped: a sidecar JSON file records what
the replay gave and how long it took. A recording made on code whose forward programs the
equivalence ledger (:mod:`dax_algos.bench.equivalence`) makes today's counts as today's
task and keeps the name from its own fingerprint.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dax_tasks.io import atomic_write

from .equivalence import forward_equivalent
from .rows import check_name

DIR = "episodes"
#: replayed and recorded final-step r_gt further apart than this are flagged
MISMATCH = 0.01
#: picture size (width, height) [pixels], animation frame rate [1/s], its largest number
#: of frames (longer episodes are subsampled evenly, the last frame kept) and the number
#: of key frames in a filmstrip
RES = (320, 240)
FPS = 8
MAX_FRAMES = 40
KEY_FRAMES = 5
#: changes whenever the drawing changes in a way the fingerprint does not see
STYLE = "scene-v1"


# ----------------------------------------------------------------------------- recording

def episode_path(out, task: str, method: str, seed: int) -> Path:
    """``out/episodes/<task>/<method>/seed<k>.npz`` (``ValueError`` for a task or method
    name that is not a file name, :func:`dax_algos.bench.rows.check_name`)."""
    return (Path(out) / DIR / check_name("task", task) / check_name("method", method)
            / f"seed{int(seed)}.npz")


class Episode(NamedTuple):
    """A recorded episode (NumPy): ``reset_key`` uint32 (2,), ``actions`` float32 (T, d),
    ``score`` its final-step r_gt, ``rollout`` / ``n_rollouts`` which evaluation rollout
    of a learner it is (0 / 1 for a planner), ``fingerprint`` the task spec's, ``budget``
    the row's (``""`` if not recorded): a later run of the other budget on the same
    directory writes the same file."""

    reset_key: np.ndarray
    actions: np.ndarray
    score: float
    rollout: int
    n_rollouts: int
    fingerprint: str
    budget: str = ""


def save_episode(path, reset_key, actions, score, fingerprint: str, rollout: int = 0,
                 n_rollouts: int = 1, budget: str = "") -> Path:
    """Write one :class:`Episode` to ``path`` (``.npz``, atomically)."""
    key = np.asarray(reset_key)
    if key.dtype != np.uint32 or key.shape != (2,):
        raise ValueError(f"reset_key must be a uint32 (2,) PRNG key, got {key.dtype} "
                         f"{key.shape}")
    arrays = dict(reset_key=key, actions=np.asarray(actions, np.float32),
                  score=np.float64(score), rollout=np.int64(rollout),
                  n_rollouts=np.int64(n_rollouts), fingerprint=np.str_(fingerprint),
                  budget=np.str_(budget))
    return atomic_write(path, lambda f: np.savez(f, **arrays))


def load_episode(path) -> Episode:
    """The :class:`Episode` in ``path``; ``ValueError`` naming the file if it is not one."""
    try:
        with np.load(path, allow_pickle=False) as z:
            ep = Episode(np.asarray(z["reset_key"]), np.asarray(z["actions"]),
                         float(z["score"]), int(z["rollout"]), int(z["n_rollouts"]),
                         str(z["fingerprint"]),
                         str(z["budget"]) if "budget" in z.files else "")
    except (OSError, ValueError, KeyError, EOFError) as err:
        raise ValueError(f"{path}: not a recorded episode ({err})") from None
    if ep.reset_key.dtype != np.uint32 or ep.reset_key.shape != (2,) \
            or ep.actions.ndim != 2 or ep.actions.dtype != np.float32:
        raise ValueError(f"{path}: not a recorded episode (reset_key {ep.reset_key.dtype} "
                         f"{ep.reset_key.shape}, actions {ep.actions.dtype} "
                         f"{ep.actions.shape})")
    return ep


def planner_reset_key(seed: int) -> np.ndarray:
    """The start key of a planner's episode for ``seed``: ``fold_in(PRNGKey(seed), 0)``."""
    return np.asarray(jax.random.fold_in(jax.random.PRNGKey(seed), 0))


def learner_reset_keys(seed: int, n_eval: int) -> np.ndarray:
    """The start keys of a learner's ``n_eval`` evaluation rollouts for ``seed``
    (:func:`dax_algos.learner.make_evaluate` from ``fold_in(PRNGKey(seed), 0)``)."""
    return np.asarray(jax.random.split(planner_reset_key(seed), n_eval))


def learner_reset_key(seed: int, n_eval: int) -> np.ndarray:
    """The start key of a learner's first evaluation rollout for ``seed``."""
    return learner_reset_keys(seed, n_eval)[0]


# ----------------------------------------------------------------------------- choosing

def _score(row) -> float:
    try:
        return float(row["score"])
    except (TypeError, ValueError):
        return math.nan


def median_row(rows: Iterable[Mapping]) -> tuple[Mapping | None, int]:
    """The row of the median-score seed among the finished (``ok``, finite score) ``rows``
    of one (task, method) and how many there were: sorted by (score, seed), the middle one,
    the lower of the two middle ones for an even count. ``(None, 0)`` if none finished."""
    ok = sorted((r for r in rows if r.get("status") == "ok" and math.isfinite(_score(r))),
                key=lambda r: (_score(r), int(r["seed"])))
    if not ok:
        return None, 0
    return ok[(len(ok) - 1) // 2], len(ok)


# ----------------------------------------------------------------------------- replay

def make_replay(env, batched: bool = False) -> Callable:
    """``replay(reset_key, actions, params) -> (states, final_r_gt)``, jitted: the start
    drawn from ``reset_key`` and every step of ``actions`` (T, d); ``states`` is the
    :class:`dax_tasks.EnvState` with a leading axis of T + 1 (the start, then after each
    step). ``batched``: the same computed under ``vmap`` over a batch of one."""

    def replay(key, actions, params):
        _, s0 = env.reset(key, params)

        def body(s, a):
            _, s2, _, _, info = env.step(s, a, params)
            return s2, (s2, info["r_gt"])

        _, (states, r_gt) = jax.lax.scan(body, s0, actions)
        states = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), s0,
                                        states)
        return states, r_gt[-1]

    if not batched:
        return jax.jit(replay)

    one = jax.jit(jax.vmap(replay, in_axes=(0, 0, None)))

    def replay_batched(key, actions, params):
        states, score = one(jnp.asarray(key)[None], jnp.asarray(actions)[None], params)
        return jax.tree_util.tree_map(lambda x: x[0], (states, score))

    return replay_batched


# ----------------------------------------------------------------------------- pictures

@dataclasses.dataclass
class Picture:
    """What the page shows of one (task, method): the median seed's episode.

    ``gif`` / ``strip``: paths relative to the output directory (``None`` with a ``note``
    saying why there is no picture); ``row_score`` the row's score, ``recorded`` the
    recorded episode's final r_gt (the row's for a planner, one rollout's for a learner),
    ``replayed`` the replay's; ``render_s`` what replaying and drawing it took when it was
    drawn [s]."""

    task: str
    method: str
    seed: int | None = None
    n_seeds: int = 0
    row_score: float = math.nan
    recorded: float = math.nan
    replayed: float = math.nan
    rollout: int = 0
    n_rollouts: int = 1
    gif: str | None = None
    strip: str | None = None
    render_s: float = 0.0
    frames: int = 0
    replay_mode: str = ""
    same_task: bool = True
    note: str = ""

    @property
    def mismatch(self) -> bool:
        """The replay does not reproduce the recorded episode's score."""
        return not abs(self.replayed - self.recorded) <= MISMATCH


def picture_key(fingerprint: str, episode: Episode) -> str:
    """12 hex digits naming the pictures of ``episode`` drawn on a task with
    ``fingerprint``: everything the pictures depend on."""
    h = hashlib.sha256()
    for part in (fingerprint, STYLE, json.dumps([RES, FPS, MAX_FRAMES, KEY_FRAMES]),
                 episode.reset_key.tobytes(), episode.actions.tobytes()):
        h.update(part if isinstance(part, bytes) else part.encode())
    return h.hexdigest()[:12]


def draw(env, states, view=None):
    """``(animation frames, filmstrip)`` (uint8 NumPy) of an episode's ``states`` (leading
    time axis): at most :data:`MAX_FRAMES` of them (evenly spaced, the first and last
    kept; drawing is the cost) in the oblique shaded view of
    :func:`dax_tasks.viz.scene_frames` with the goal as a faint overlay, and
    :data:`KEY_FRAMES` key frames beside the goal alone (:func:`dax_tasks.viz.
    goal_frame`, with the colliders of the episode's start). ``view``: a
    :class:`dax_tasks.viz.SceneView` (default ``SceneView.for_env(env)``)."""
    from dax_tasks import viz

    view = viz.SceneView.for_env(env) if view is None else view
    n = int(np.shape(states.t)[0])
    keep = viz.subsample(n, MAX_FRAMES)
    frames = viz.scene_frames(env, jax.tree_util.tree_map(lambda x: x[keep], states),
                                 view=view, res=RES, goal=True)
    start = jax.tree_util.tree_map(lambda x: x[0], states)
    goal = viz.goal_frame(env, start, view=view, res=RES)
    return frames, viz.filmstrip(frames, k=KEY_FRAMES, goal_frame=goal)


def render_picture(out: Path, env, episode: Episode, task: str, method: str, seed: int,
                   replays: dict, params=None, fingerprint: str | None = None) -> dict:
    """Replay ``episode`` on ``env``, draw it and write its pictures under ``out`` (the
    GIF, the filmstrip PNG, then the sidecar JSON, each atomically); returns the sidecar's
    contents. ``replays`` caches the jitted replays per (task, batched) and the view per
    (task, "view"). ``fingerprint``: the one the pictures are named by (default the env's;
    the recording's where the two are forward-equivalent, so the names stay)."""
    from dax_tasks import viz

    params = env.default_params if params is None else params
    t0 = time.perf_counter()
    key = picture_key(env.spec.fingerprint() if fingerprint is None else fingerprint,
                      episode)
    base = Path(out) / DIR / task / method / f"seed{seed}-{key}"
    mode = "unbatched"
    for batched in (False, True):
        fn = replays.get((task, batched))
        if fn is None:
            fn = replays[(task, batched)] = make_replay(env, batched)
        states, score = jax.device_get(fn(jnp.asarray(episode.reset_key),
                                          jnp.asarray(episode.actions), params))
        score = float(score)
        if abs(score - episode.score) <= MISMATCH:
            break
        mode = "vmap over a batch of one"
    if (task, "view") not in replays:  # one view per task: its methods framed alike
        replays[(task, "view")] = viz.SceneView.for_env(env, params)
    frames, strip = draw(env, states, replays[(task, "view")])
    viz.save_animation(frames, base.with_suffix(".gif"), fps=FPS)
    viz.save_png(strip, base.with_suffix(".png"), optimize=False)
    meta = dict(seed=int(seed), key=key, replayed=score, recorded=episode.score,
                replay_mode=mode, frames=int(len(frames)),
                render_s=round(time.perf_counter() - t0, 3),
                gif=base.with_suffix(".gif").name, strip=base.with_suffix(".png").name)
    atomic_write(base.with_suffix(".json"), json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return meta


def _cached(base: Path) -> dict | None:
    side = base.with_suffix(".json")
    if not side.is_file():
        return None
    try:
        meta = json.loads(side.read_text())
    except ValueError:
        return None
    if not isinstance(meta, dict) or not all((base.parent / str(meta.get(k, ""))).is_file()
                                             for k in ("gif", "strip")):
        return None
    return meta


def episode_pictures(out, rows: list[Mapping], make_env: Callable[[str], object],
                     tasks: Iterable[str], methods: Iterable[str],
                     prune: bool = True) -> list[Picture]:
    """One :class:`Picture` per (task, method) with rows, in the order of ``tasks`` and
    ``methods``: the median seed's episode, drawn unless its pictures are already there.
    ``make_env(task)`` builds the task as the run did (called only when something is
    drawn). ``prune``: remove the pictures of a (task, method) that are no longer shown
    (the median seed changed when seeds were added)."""
    out = Path(out)
    by_pair: dict = {}
    for r in rows:
        by_pair.setdefault((r["task"], r["method"]), []).append(r)
    envs: dict = {}
    replays: dict = {}
    pictures = []
    for t in tasks:
        for m in methods:
            if (t, m) not in by_pair:
                continue
            check_name("task", t), check_name("method", m)  # they become paths below
            pic = _picture(out, t, m, by_pair[(t, m)], make_env, envs, replays)
            pictures.append(pic)
            if prune:
                _prune(out / DIR / t / m, {pic.gif, pic.strip})
    return pictures


def _picture(out, t, m, rows, make_env, envs, replays) -> Picture:
    row, n = median_row(rows)
    pic = Picture(t, m, n_seeds=n)
    if row is None:
        pic.note = "no finished run"
        return pic
    seed = int(row["seed"])
    pic.seed, pic.row_score = seed, _score(row)
    path = episode_path(out, t, m, seed)
    if not path.is_file():
        pic.note = f"seed {seed}'s episode was not recorded (a run from before recordings)"
        return pic
    try:
        episode = load_episode(path)
        if episode.budget and episode.budget != row.get("budget", episode.budget):
            pic.note = (f"seed {seed}'s recording is of the {episode.budget} budget (a later "
                        f"run on this directory), not of this row's")
            return pic
        pic.recorded, pic.rollout, pic.n_rollouts = (episode.score, episode.rollout,
                                                     episode.n_rollouts)
        if t not in envs:
            envs[t] = make_env(t)
        env = envs[t]
        today = env.spec.fingerprint()
        # a recording on code whose forward programs are today's replays as it ran: it
        # counts as today's task and keeps the name it was drawn under
        pic.same_task = forward_equivalent(episode.fingerprint, today)
        fingerprint = episode.fingerprint if pic.same_task else today
        base = out / DIR / t / m / f"seed{seed}-{picture_key(fingerprint, episode)}"
        meta = _cached(base)
        if meta is None:
            meta = render_picture(out, env, episode, t, m, seed, replays,
                                  fingerprint=fingerprint)
    except Exception as err:  # noqa: BLE001 - the page says why, the report goes on
        pic.note = "not drawn: " + " ".join(f"{type(err).__name__}: {err}".split())[:300]
        return pic
    rel = f"{DIR}/{t}/{m}/"
    pic.gif, pic.strip = rel + meta["gif"], rel + meta["strip"]
    pic.replayed, pic.render_s = float(meta["replayed"]), float(meta["render_s"])
    pic.frames, pic.replay_mode = int(meta["frames"]), str(meta["replay_mode"])
    return pic


def _prune(directory: Path, keep: set) -> None:
    """Delete the pictures in ``directory`` (``seed<k>-<hash>.gif/.png/.json``) other than
    those of ``keep`` (relative paths)."""
    if not directory.is_dir():
        return
    stems = {Path(k).stem for k in keep if k}
    for p in directory.glob("seed*-*.*"):
        if p.suffix in (".gif", ".png", ".json") and p.stem not in stems:
            p.unlink(missing_ok=True)
