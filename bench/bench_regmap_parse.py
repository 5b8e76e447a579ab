"""Register-map parse time against the map's size: is the parser linear? (issue 51)

A hostile map of 30000 registers kept ``rig safe`` busy for more than 300 s: the parser looked up
each register's line numbers by scanning every register (quadratic). This script writes maps of
1000, 4000 and 30000 registers (a supply's six roles, then role "none" registers at consecutive
addresses) and prints, for each, the time of ``regmaps.load_map`` against a baseline measured in
the same run on the same text: ``tomllib.loads`` alone (the least any parser of the file does).
A linear parser keeps the ratio about constant as the size grows; a quadratic one's ratio grows
with the size.

Maps beyond ``regmaps.MAX_REGISTERS`` are refused at load (that refusal is timed too, "refused");
the figure "parsed" lifts the cap for this measurement only, to show the parse itself is linear.

Run: ``nice .venv/bin/python bench/bench_regmap_parse.py [--sizes 1000,4000,30000]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import regmaps

HEAD = """[device]
kind = "supply"
model = "bench"
v_max = 30.0
i_max = 10.0

"""
ROLES = ("output", "v_set", "i_set", "v_out", "i_out", "protection")


def map_text(n: int) -> str:
    """A valid supply map of ``n`` registers (uint16, scale 100, addresses 0..n-1)."""
    parts = [HEAD]
    for i in range(n):
        role = ROLES[i] if i < len(ROLES) else "none"
        parts.append(
            f'[[registers]]\nname = "r{i}"\naddress = {i}\ntype = "uint16"\nscale = 100\n'
            f'access = "rw"\nrole = "{role}"\n\n'
        )
    return "".join(parts)


def best_of(fn: object, repeat: int) -> float:
    """The shortest of ``repeat`` calls of ``fn`` (s): the least disturbed by other work."""
    assert callable(fn)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", default="1000,4000,30000", help="register counts, comma-separated"
    )
    parser.add_argument("--repeat", type=int, default=3, help="timed calls per figure (best kept)")
    args = parser.parse_args()
    cap = regmaps.MAX_REGISTERS
    print(f"register cap (regmaps.MAX_REGISTERS): {cap}")
    print(f"{'registers':>9} {'tomllib s':>10} {'parsed s':>10} {'ratio':>7} {'refused s':>10}")
    with tempfile.TemporaryDirectory() as tmp:
        for n in (int(s) for s in args.sizes.split(",")):
            text = map_text(n)
            path = Path(tmp) / f"bench-{n}.toml"
            path.write_text(text, encoding="utf-8")
            base = best_of(lambda text=text: tomllib.loads(text), args.repeat)

            def parse(path: Path = path) -> None:
                regmaps._load.cache_clear()  # every call parses the file again
                regmaps.load_map(str(path))

            refused = "-"
            if n > cap:

                def refuse(parse: object = parse) -> None:
                    try:
                        parse()  # type: ignore[operator]
                    except regmaps.RegisterMapError:
                        return
                    raise AssertionError("a map beyond the cap was not refused")

                refused = f"{best_of(refuse, args.repeat):10.3f}"
                regmaps.MAX_REGISTERS = n
            try:
                parsed = best_of(parse, args.repeat)
            finally:
                regmaps.MAX_REGISTERS = cap
            print(f"{n:>9} {base:>10.3f} {parsed:>10.3f} {parsed / base:>7.1f} {refused:>10}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
