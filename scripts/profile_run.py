"""Profile a ``recon3d run``: the top functions of each stage (cProfile).

Every stage of :data:`recon3d.pipeline.run.STAGES` is run under its own profiler, in
this process, through the same command line as ``recon3d run``; after the run each
stage prints its wall time and its ``--top`` functions by own time (``tottime``: where
the time is spent, not who called it), with their cumulative time beside.

``--quick`` profiles the IGN village (71k points) with a tenth of the rows.

    .venv/bin/python scripts/profile_run.py [--top 12] [--sort cumulative] [--stages dsm,ground,dtm] -- ARGS OF recon3d run
    .venv/bin/python scripts/profile_run.py -- ../shared/data/lidar/delft_ahn3_strip.laz --crs EPSG:7415 -o /tmp/out
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time

import _bench

QUICK_FILE = _bench.SHARED / "lidar" / "ign_village_2154.laz"


def profiled_stages(names: set[str] | None) -> dict[str, tuple[float, cProfile.Profile]]:
    """Wrap the pipeline's stages in profilers; returns the (filled during the run) results by stage."""
    from recon3d.pipeline import run

    results: dict[str, tuple[float, cProfile.Profile]] = {}

    def wrap(name, stage):
        def profiled(state):
            profile = cProfile.Profile()
            start = time.perf_counter()
            profile.enable()
            try:
                return stage(state)
            finally:
                profile.disable()
                results[name] = (time.perf_counter() - start, profile)

        return profiled

    run.STAGES[:] = [(n, wrap(n, f) if names is None or n in names else f) for n, f in run.STAGES]
    return results


def report(results: dict[str, tuple[float, cProfile.Profile]], top: int, sort: str = "tottime") -> None:
    total = sum(seconds for seconds, _ in results.values())
    print(f"\nprofiled stages: {total:.2f} s")
    for name, (seconds, profile) in results.items():
        print(f"\n== {name}: {seconds:.2f} s")
        text = io.StringIO()
        stats = pstats.Stats(profile, stream=text)
        stats.sort_stats(sort).print_stats(top)
        lines = text.getvalue().splitlines()
        start = next((i for i, line in enumerate(lines) if line.lstrip().startswith("ncalls")), 0)
        print("\n".join(line for line in lines[start:] if line.strip()))


def main() -> int:
    argv = sys.argv[1:]
    run_args = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--top", type=int, default=12, help="functions shown per stage (default: %(default)s)")
    parser.add_argument(
        "--sort", choices=("tottime", "cumulative"), default="tottime",
        help="order: own time (where it is spent) or cumulative (which call costs it); default %(default)s",
    )
    parser.add_argument("--stages", help="comma-separated stage names to profile (default: all)")
    _bench.add_quick(parser)
    args = parser.parse_args(own)
    with tempfile.TemporaryDirectory() as tmp:
        if args.quick:
            run_args = [str(_bench.require(QUICK_FILE, "LiDAR file")), "-o", f"{tmp}/out"]
            args.stages = args.stages or "dsm,ground,dtm"
        if not run_args:
            _bench.refuse("give the arguments of `recon3d run` after --")
        from recon3d import cli

        names = set(args.stages.split(",")) if args.stages else None
        results = profiled_stages(names)
        sys.argv = ["recon3d", "run", *run_args]
        try:
            cli.main()
        except SystemExit as exc:
            if exc.code not in (0, None):
                return int(exc.code) if isinstance(exc.code, int) else 1
        report(results, args.top, args.sort)
    return 0


if __name__ == "__main__":
    _bench.guard(main)
