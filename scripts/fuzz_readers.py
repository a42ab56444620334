"""Fuzz every reader with many damaged files: each must read or raise recon3d's own error.

Runs the generators of ``tests/test_fuzz_readers.py`` (a valid small LAS, GeoTIFF,
CityJSON, PLY and OSSIM RPC file; random truncations, byte flips and extreme bytes)
with many more examples than the suite, and prints per reader the cases tried and any
exception that was not a :class:`recon3d.errors.Recon3dError` (none is the target).

    .venv/bin/python scripts/fuzz_readers.py              # 10,000 per reader
    .venv/bin/python scripts/fuzz_readers.py --examples 500 --only las tif
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from hypothesis import HealthCheck, given, settings  # noqa: E402

from recon3d.errors import Recon3dError  # noqa: E402
from test_fuzz_readers import READERS, _write, damage, spoil  # noqa: E402


def fuzz(kind: str, examples: int) -> tuple[int, collections.Counter]:
    make, read, suffix = READERS[kind]
    base = make()
    tried, bad = 0, collections.Counter()
    with tempfile.TemporaryDirectory() as tmp:

        @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
        @given(damage(len(base)))
        def check(mutation):
            nonlocal tried
            tried += 1
            try:
                read(_write(Path(tmp), spoil(base, *mutation), suffix))
            except Recon3dError:
                pass
            except Exception as exc:  # what the target forbids: count it, keep fuzzing
                bad[f"{type(exc).__name__}: {str(exc)[:80]}"] += 1

        check()
    return tried, bad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=10_000)
    parser.add_argument("--only", nargs="*", choices=sorted(READERS))
    args = parser.parse_args()
    for kind in args.only or sorted(READERS):
        t = time.perf_counter()
        tried, bad = fuzz(kind, args.examples)
        print(f"{kind:<9} {tried:>6} damaged files, {sum(bad.values())} foreign exceptions, {time.perf_counter() - t:.0f} s")
        for what, n in bad.most_common(10):
            print(f"          {n:>6} x {what}")


if __name__ == "__main__":
    main()
