"""Building a scene's Gaussian-splatting model: one pipeline for the demo, the experiments and the tests.

A :class:`ModelRecipe` says how; :func:`build_model` records round 1 as a nerfstudio dataset (``<folder>/round1/``),
trains, and writes ``<folder>/model.ply`` and ``<folder>/train.json`` (recipe, config, history, wall time, held-out
PSNR); with ``cache`` the folder is ``<cache>/<scene>-<key>`` (:meth:`ModelRecipe.key`), loaded instead of trained
when it exists.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
import hashlib
import json
from pathlib import Path
import shutil
import time

from gsrmr_common.nerfstudio import holdout_split, read_dataset
from gsrmr_sim.world.recorder import record_round1, with_resolution
from gsrmr_sim.world.scene import Scene, load_scene, scene_cache_text
from gsrmr_splat.compact import CompactConfig, Compactor
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.train import HistoryRow, Trainer
from gsrmr_splat.train_config import TrainConfig

CACHE_VERSION = 1  # bump when the pipeline changes what a recipe builds


@dataclass(frozen=True)
class ModelRecipe:
    """How to build one scene's model (image sizes in pixels, times in seconds)."""

    scene: str = "sandbox"
    frames: int = 144  # H, mapping-round frames
    width: int | None = None  # recording size (None: the scene's camera)
    height: int | None = None
    seed: int = 0  # recording jitter seed (the trainer's seed is config.seed)
    config: TrainConfig = field(default_factory=TrainConfig)
    iterations: int | None = None  # training steps (None: config.iterations, which also sets the lr decay)
    time_budget_s: float | None = None  # stop training at this wall time (whichever comes first)
    holdout_every: int = 8  # every n-th frame is held out for the PSNR (0: none)
    eval_every: int = 0  # held-out PSNR every n iterations (0: at the end only)

    def key(self) -> str:
        """Cache key: the scene (:func:`scene_cache_text`), this recipe and :data:`CACHE_VERSION`, hashed."""
        recipe = asdict(self)
        recipe["config"] = self.config.to_dict()
        blob = scene_cache_text(self.scene) + json.dumps(recipe, sort_keys=True, default=str)
        return hashlib.sha256(f"{blob}v{CACHE_VERSION}".encode()).hexdigest()[:12]

    def recorded_scene(self) -> Scene:
        """The scene at the recording size."""
        return with_resolution(load_scene(self.scene), self.width, self.height)


@dataclass
class BuiltModel:
    """A built (or cached) model and where it lives."""

    model: GaussianModel
    folder: Path
    info: dict  # train.json (compact-<tol>.json for a compacted model)
    ply_name: str = "model.ply"

    @property
    def path(self) -> Path:
        """The model's ``.ply``."""
        return self.folder / self.ply_name

    @property
    def heldout_psnr_db(self) -> float:
        """Held-out PSNR at the end of training (NaN without a held-out split)."""
        return float(self.info.get("heldout_psnr_db", float("nan")))


def history_rows(history: list) -> list[dict]:
    """Trainer history as dicts: iteration, elapsed_s (wall), cpu_s, train_loss, heldout_psnr_db, gaussians."""
    return [{"iteration": int(h.iteration), "elapsed_s": float(h.wall_s), "cpu_s": float(h.cpu_s),
             "train_loss": float(h.loss), "heldout_psnr_db": float(h.test_psnr_db),
             "gaussians": int(h.num_gaussians)} for h in history if isinstance(h, HistoryRow)]


def build_model(recipe: ModelRecipe, *, cache: str | Path | None = None, folder: str | Path | None = None,
                log: Callable[[str], None] = print) -> BuiltModel:
    """Record round 1 and train (or load the cached result); exactly one of ``cache`` and ``folder``."""
    if (cache is None) == (folder is None):
        raise ValueError("build_model: give either cache (reused by key) or folder (always built)")
    out = Path(folder) if folder is not None else Path(cache) / f"{recipe.scene}-{recipe.key()}"  # type: ignore[arg-type]
    model_path, info_path = out / "model.ply", out / "train.json"
    if cache is not None and model_path.exists() and info_path.exists():
        log(f"{recipe.scene}: GS model cached: {model_path}")
        return BuiltModel(GaussianModel.load_ply(model_path), out, json.loads(info_path.read_text()))
    r1 = out / "round1"
    if r1.exists():
        shutil.rmtree(r1)
    t0 = time.perf_counter()
    dataset = record_round1(recipe.recorded_scene(), r1, frames=recipe.frames, seed=recipe.seed)
    log(f"{recipe.scene}: round 1 recorded: {recipe.frames} frames in {time.perf_counter() - t0:.1f} s → {dataset}")
    t0 = time.perf_counter()
    trainer = Trainer.from_dataset(dataset, recipe.config, holdout_every=recipe.holdout_every)
    initial_psnr = trainer.evaluate()
    model = trainer.train(recipe.iterations, eval_every=recipe.eval_every, progress=False,
                          time_budget_s=recipe.time_budget_s)
    wall = time.perf_counter() - t0
    hist = history_rows(trainer.state.history)
    last = hist[-1] if hist else {}
    info = {"recipe": {**asdict(recipe), "config": recipe.config.to_dict()}, "config": recipe.config.to_dict(),
            "initial_heldout_psnr_db": initial_psnr, "history": hist, "wall_s": wall,
            "iterations": last.get("iteration"), "cpu_s": last.get("cpu_s"),
            "heldout_psnr_db": last.get("heldout_psnr_db"), "train_frames": len(trainer.frames),
            "heldout_frames": len(trainer.test_frames), "gaussians": model.num_gaussians}
    log(f"{recipe.scene}: GS model trained: {model.num_gaussians} Gaussians, {last.get('iteration')} iterations, "
        f"held-out PSNR {last.get('heldout_psnr_db', float('nan')):.2f} dB in {wall:.1f} s")
    out.mkdir(parents=True, exist_ok=True)
    model.save_ply(out / "model.tmp.ply")
    (out / "model.tmp.ply").replace(model_path)
    info_path.write_text(json.dumps(info, indent=1, default=str))
    return BuiltModel(model, out, info)


def compact_built(built: BuiltModel, recipe: ModelRecipe, max_psnr_drop_db: float,
                  log: Callable[[str], None] = print) -> BuiltModel:
    """The built model compacted to the smallest one within ``max_psnr_drop_db`` of its held-out PSNR
    (:mod:`gsrmr_splat.compact`), cached beside it as ``model-compact-<tol>.ply`` +
    ``compact-<tol>.json``. The info also holds both models' held-out PSNR at the dataset's own (full)
    resolution, which is the live image size."""
    tag = f"{max_psnr_drop_db:g}"
    path, info_path = built.folder / f"model-compact-{tag}.ply", built.folder / f"compact-{tag}.json"
    if path.exists() and info_path.exists():
        log(f"{recipe.scene}: compacted GS model cached: {path}")
        return BuiltModel(GaussianModel.load_ply(path), built.folder, json.loads(info_path.read_text()), path.name)
    train, test = holdout_split(read_dataset(built.folder / "round1"), recipe.holdout_every)
    result = Compactor(train, test, recipe.config, CompactConfig(max_psnr_drop_db=max_psnr_drop_db)).run(built.model)
    full_res = Compactor(train, test, replace(recipe.config, resolution=None))
    info = {**result.summary(), "max_psnr_drop_db": max_psnr_drop_db,
            "heldout_psnr_db": result.heldout_psnr_after_db,
            "heldout_psnr_full_res_before_db": full_res.evaluate(built.model),
            "heldout_psnr_full_res_after_db": full_res.evaluate(result.model),
            "full_res_width": test[0].camera.width if test else None}
    log(f"{recipe.scene}: GS model compacted: {result.gaussians_before} → {result.gaussians_after} Gaussians, "
        f"held-out PSNR {result.heldout_psnr_before_db:.2f} → {result.heldout_psnr_after_db:.2f} dB "
        f"(at {info['full_res_width']} px: {info['heldout_psnr_full_res_before_db']:.2f} → "
        f"{info['heldout_psnr_full_res_after_db']:.2f} dB) in {result.wall_s:.0f} s")
    result.model.save_ply(built.folder / f"model-compact-{tag}.tmp.ply")
    (built.folder / f"model-compact-{tag}.tmp.ply").replace(path)
    info_path.write_text(json.dumps(info, indent=1))
    return BuiltModel(result.model, built.folder, info, path.name)


#: The live system's model recipe defaults (``gsrmr-demo``): train at 160 px wide (the round-1 frames are
#: recorded at the scene camera's size, 320×240, which is also where the model is rendered live), SH degree 0,
#: at most 100k Gaussians, for a fixed number of steps (deterministic: the same model on any load), then
#: compacted within 0.3 dB of held-out PSNR. The sandbox's trade (docs/results.md, "The live model"): 1000 /
#: 1500 / 2000 / 3000 steps → 32.9 / 35.0 / 35.8 / 37.7 dB held out for 170 / 245 / 336 / 524 CPU s.
LIVE_TRAIN_WIDTH_PX = 160
LIVE_BUDGET = 100_000
LIVE_MAX_PSNR_DROP_DB = 0.3
DEFAULT_TRAIN_ITERATIONS = 2000


def live_recipe(scene_name: str, *, frames: int | None = None, train_seconds: float | None = None,
                iterations: int | None = None, width: int | None = None, budget: int | None = None) -> ModelRecipe:
    """The recipe of the model the live system renders (``gsrmr-demo``, ``gsrmr-experiments``).

    Round-1 frames at the scene camera's size (the live render size); training at ``width`` px (SH degree 0,
    at most ``budget`` Gaussians). Training stops after ``iterations`` steps (deterministic: the learning-rate
    decay and densification follow the count, no opacity reset, held-out PSNR every 500 steps) or, only when
    asked for, after ``train_seconds`` of wall time (then the model depends on the machine and its load).
    Anything not given comes from the scene's ``model`` section (scene YAML), else
    :data:`DEFAULT_TRAIN_ITERATIONS` steps at 160 px with 100k Gaussians."""
    scene = load_scene(scene_name)
    if iterations is None and train_seconds is None:
        iterations, train_seconds = scene.model_iterations, scene.model_train_seconds
        if iterations is None and train_seconds is None:
            iterations = DEFAULT_TRAIN_ITERATIONS
    width = width or scene.model_train_width_px or LIVE_TRAIN_WIDTH_PX
    budget = budget or scene.model_budget or LIVE_BUDGET
    # trained over the background the server composes the render over (ServerParameters.background_rgb = the
    # scene's): over black, where the model is not opaque the live render showed grey the training never saw
    config = TrainConfig(resolution=width, sh_degree=0, budget=budget, background=tuple(scene.background))
    if scene.model_init_points:
        config = replace(config, init_points=scene.model_init_points)
    if iterations is not None:  # the schedule scaled to the count
        config = replace(config, iterations=iterations, densify_until=min(config.densify_until, (2 * iterations) // 3),
                         opacity_reset_interval=max(config.opacity_reset_interval, iterations + 1))
    return ModelRecipe(scene=scene_name, frames=frames or scene.frames, config=config,
                       iterations=iterations or 100_000, time_budget_s=train_seconds, holdout_every=8,
                       eval_every=500 if iterations is not None else 0)


def live_model(recipe: ModelRecipe, cache: str | Path, *, max_psnr_drop_db: float | None = LIVE_MAX_PSNR_DROP_DB,
               log: Callable[[str], None] = print) -> BuiltModel:
    """Build (or load) ``recipe``'s model and, with ``max_psnr_drop_db``, its compacted version (cached)."""
    built = build_model(recipe, cache=cache, log=log)
    return built if max_psnr_drop_db is None else compact_built(built, recipe, max_psnr_drop_db, log=log)
