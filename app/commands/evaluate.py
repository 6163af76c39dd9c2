"""``smartroom eval --recording DIR --results DIR``: score results against ground truth."""
from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("--recording", required=True, metavar="DIR", help="recording folder with groundtruth.jsonl")
    p.add_argument("--results", required=True, metavar="DIR", help="results folder of smartroom run")


def main(args) -> int:
    from pathlib import Path

    from app.errors import InputError
    from app.recording import Recording

    rec = Recording(args.recording)
    if rec.groundtruth() is None:
        raise InputError(f"{args.recording}: has no groundtruth.jsonl to score against")
    results = Path(args.results)
    if not results.is_dir():
        raise InputError(f"{results}: results folder not found")
    scored = [f for f in ("tracks.jsonl", "poses.jsonl") if (results / f).is_file()]
    if not scored:
        raise InputError(f"{results}: holds no tracks.jsonl or poses.jsonl to score")
    raise InputError(f"{results}: scoring of {', '.join(scored)} is not implemented yet")
