"""``smartroom bench grabber``: what one camera costs the grabber per frame, at VGA and
at HD (issue 8: four 1920x1088 views, 25 MB a frame set, made the grabber the pipeline's
bottleneck at 10 fps).

For each size it writes a short synthetic video per camera (moving textured content,
mp4v) and measures per camera and frame: decoding, the reduction to the size the
segmentation works at (``smartroom``'s grabber sends frames already reduced), encoding
the bus message, and its size; then the wall time of one frame set with the cameras
decoded one after the other and in parallel threads (OpenCV releases the GIL).
"""
from __future__ import annotations

import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from app.messages import Frame, encode
from app.segmentation import shrink

__all__ = ["run", "format_table", "HEADER"]

SIZES = ((640, 480), (1920, 1088))
HEADER = ("size        scale | decode ms | reduce ms | encode ms | message MB | set of 4: serial ms | parallel ms\n"
          "---------------------------------------------------------------------------------------------------")


def _write_video(path: Path, size, frames: int, seed: int) -> None:
    w, h = size
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.integers(0, 255, (h // 16 + 1, w // 16 + 1, 3), dtype=np.uint8), (w, h))
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (w, h))
    for i in range(frames):
        img = np.roll(base, 7 * i, axis=1)
        cv2.rectangle(img, (i * 9 % w, h // 4), (i * 9 % w + w // 8, h - h // 8), (40, 200, 240), -1)
        vw.write(img)
    vw.release()


def _decode_all(paths) -> list[list[np.ndarray]]:
    out = []
    for p in paths:
        cap = cv2.VideoCapture(str(p))
        frames = []
        while True:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(img)
        cap.release()
        out.append(frames)
    return out


def _timed_reads(path, n: int) -> list[float]:
    cap = cv2.VideoCapture(str(path))
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        ok, _img = cap.read()
        if not ok:
            break
        times.append((time.perf_counter() - t0) * 1e3)
    cap.release()
    return times


def _set_wall(paths, n: int, parallel: bool) -> float:
    caps = [cv2.VideoCapture(str(p)) for p in paths]
    pool = ThreadPoolExecutor(len(caps)) if parallel else None
    walls = []
    for _ in range(n):
        t0 = time.perf_counter()
        if pool is not None:
            list(pool.map(lambda c: c.read(), caps))
        else:
            for c in caps:
                c.read()
        walls.append((time.perf_counter() - t0) * 1e3)
    for c in caps:
        c.release()
    if pool is not None:
        pool.shutdown()
    return float(np.median(walls))


def run(frames: int = 40, cameras: int = 4, scales=(1, 4)) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="smartroom-bench-grabber-") as tmp:
        for size in SIZES:
            paths = [Path(tmp) / f"{size[0]}x{size[1]}-cam{c}.mp4" for c in range(cameras)]
            for c, p in enumerate(paths):
                _write_video(p, size, frames, seed=c)
            decode = float(np.median(_timed_reads(paths[0], frames)))
            images = _decode_all(paths[:1])[0]
            serial = _set_wall(paths, frames, parallel=False)
            parallel = _set_wall(paths, frames, parallel=True)
            for scale in scales:
                t_red, t_enc, nbytes = [], [], []
                for img in images:
                    t0 = time.perf_counter()
                    small = shrink(img, scale) if scale > 1 else img
                    t1 = time.perf_counter()
                    payload = encode(Frame(frame=0, camera="cam0", cameras=["cam0"], scale=scale, image=small))
                    t2 = time.perf_counter()
                    t_red.append((t1 - t0) * 1e3)
                    t_enc.append((t2 - t1) * 1e3)
                    nbytes.append(len(payload))
                rows.append({"size": f"{size[0]}x{size[1]}", "scale": scale, "decode_ms": round(decode, 3),
                             "reduce_ms": round(float(np.median(t_red)), 3),
                             "encode_ms": round(float(np.median(t_enc)), 3),
                             "message_mb": round(float(np.median(nbytes)) / 1e6, 3),
                             "set_serial_ms": round(serial, 2), "set_parallel_ms": round(parallel, 2),
                             "cameras": cameras})
    return rows


def format_table(rows: list[dict]) -> str:
    lines = [HEADER]
    for r in rows:
        lines.append(f"{r['size']:<11} {r['scale']:>5} | {r['decode_ms']:>9.2f} | {r['reduce_ms']:>9.2f} | "
                     f"{r['encode_ms']:>9.2f} | {r['message_mb']:>10.3f} | {r['set_serial_ms']:>19.1f} | "
                     f"{r['set_parallel_ms']:>11.1f}")
    return "\n".join(lines)
