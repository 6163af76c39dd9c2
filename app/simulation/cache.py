"""The built-in default source of ``smartroom run``: a simulated recording rendered once
into a cache folder and replayed from there (the random scenes of ``smartroom bench
accuracy`` too: scene ``random``, the seed drawing the scene).

The folder is ``$SMARTROOM_CACHE/<scene>-<seconds>s-<fps>fps-seed<k>-v<renderer
version>`` (``SMARTROOM_CACHE`` defaults to ``~/.cache/smartroom/recordings``). It is
written as ``<folder>.partial`` and renamed when complete, so an interrupted render is
redone; a lock file keeps two processes from rendering the same folder at once.
"""
from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

__all__ = ["cache_root", "cache_path", "default_recording", "can_render_live", "DEFAULT_SECONDS"]

DEFAULT_SECONDS = 30.0


def cache_root() -> Path:
    env = os.environ.get("SMARTROOM_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "smartroom" / "recordings"


def cache_path(scene: str = "meeting3", seconds: float = DEFAULT_SECONDS, fps: float = 25.0, seed: int = 0,
               zenithal: bool = False) -> Path:
    """Where the cached recording of these settings lives."""
    from app.simulation.render import RENDERER_VERSION
    name = f"{scene}-{seconds:g}s-{fps:g}fps-seed{int(seed)}{'-zenithal' if zenithal else ''}-v{RENDERER_VERSION}"
    if scene == "random":   # a random scene is also what the generator drew from the seed
        from app.simulation.random_scene import GENERATOR_VERSION
        name += f"-g{GENERATOR_VERSION}"
    return cache_root() / name


def _complete(path: Path) -> bool:
    return (path / "calibration.yaml").is_file() and (path / "simulation.json").is_file()


def default_recording(scene: str = "meeting3", seconds: float = DEFAULT_SECONDS, fps: float = 25.0, seed: int = 0,
                      zenithal: bool = False, progress=None) -> Path:
    """The cached recording of a scene, rendered first if needed (progress with ETA on
    stderr unless ``progress`` is given). Returns the recording folder."""
    from app.simulation.scenes import get_scene
    from app.simulation.simulator import RANDOM, print_progress, render_recording

    if scene != RANDOM:
        get_scene(scene)  # unknown scene: InputError before anything else
    path = cache_path(scene, seconds, fps, seed, zenithal)
    if _complete(path):
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process may be rendering it: wait
        try:
            if _complete(path):
                return path
            render_recording(scene, path, seconds=seconds, fps=fps, seed=seed, zenithal=zenithal,
                             progress=progress or print_progress(f"rendering the simulated room ({scene}, once)"),
                             overwrite=True)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return path


def can_render_live(scene: str = "meeting3", fps: float = 25.0, frames: int = 12, zenithal: bool = False,
                    margin: float = 1.3) -> bool:
    """Whether this machine renders the scene faster than ``fps`` (with a ``margin``),
    measured on a few frames after warming up; if not, use :func:`default_recording`."""
    from app.simulation.simulator import Simulator

    sim = Simulator(scene, fps=fps, zenithal=zenithal)
    sim.render(0)  # compile / warm up
    start = time.perf_counter()
    n = min(frames, max(1, sim.frame_count() - 1))
    for i in range(1, n + 1):
        sim.render(i * 7 % sim.frame_count())
    per_frame = (time.perf_counter() - start) / n
    return per_frame * margin < 1.0 / fps
