"""Fuzz the procedure language with Hypothesis: every text either parses into a procedure whose
plan holds only finite numbers, or is refused with the language's one-line error; never another
exception, never a hang.

    .venv/bin/python bench/fuzz_procedures.py [--examples 10000] [--seed 0]

prints the examples run, how many parsed, the rejections by category and the time.
``tests/engine/test_procedure_hardening.py`` runs the same property with 200 examples.

The texts are procedures assembled from the real vocabulary (every step kind and load profile,
each parameter at its default, bounds or a hostile value: nan, inf, 1e999, 400- and 5000-digit
integers, tags, placeholders, aliases, files outside the folder), sometimes with bulk that reaches
a limit (10 001 and 20 000 steps, a file over 1 MiB, alias bombs, deep nesting, an 8-day
procedure, a million load set-points), sometimes edited at random, sometimes plain random text or
bytes. A harness, not part of the product: the script imports nothing of the tests, the tests
import it as ``bench.fuzz_procedures``.
"""

from __future__ import annotations

import argparse
import math
import re
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from rig.errors import UserInputError
from rig.procedure.language import parse_procedure
from rig.procedure.plan import compile_plan, step_duration
from rig.steps import KINDS
from rig.steps.load_profiles import LOAD_PROFILES
from rig.steps.vocabulary import (
    MAX_CSV_PROFILE_BYTES,
    MAX_CSV_PROFILE_ROWS,
    MAX_STEPS,
    MAX_TOTAL_DURATION_S,
    NotFiniteError,
    StepParam,
)

PARSE_BOUND_S = 5.0
"""Most CPU time a parse may take (s) before the property counts it as a hang; the slowest bulk case
(20 000 steps) is refused in about 0.2 s."""

ISS_TLE = (
    '["1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991",'
    ' "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482"]'
)
HOSTILE = [".nan", ".NaN", ".inf", "-.inf", "+.inf", "1.0e+999", "-1.0e+999", "!!float nan",
           "!!float inf", "!!float 1e999", "!!float abc", "!!int x", "'nan'", "'inf'", "'-inf'",
           "'1e999'", "9" * 400, "9" * 5000, "2001-02-30", "!!binary AAA",
           "!!python/object/apply:os.system ['true']", "'{x}'", "'{y}'", "'{nope}'",
           "'{x:>999999999}'", "'{x.__class__}'", "'{'", "null", "yes", "no", "~", "[]", "{}",
           "[0, 0, .nan]", "[1, 2, 3]", "[10, 30]", "[30, 10]", "[.inf, 1]", "'text'", "*a0",
           "&a0 1", "&a0 [1, 2]", "[*a0, *a0]", "-1", "0", "1e6", "1.0e+300", "2147483648"]  # fmt: skip
FILES = ["profile.csv", "sub/x.csv", "inlink.csv", "nan.csv", "../outside.csv", "link.csv",
         "up/outside.csv", "/etc/passwd", "missing.csv", "sub", "'{x}'", "sub/../profile.csv",
         "rows.csv", "huge.csv"]  # fmt: skip
OVERRIDES = ["nan", "inf", "-inf", "1e999", "-1e999", "5", "0.5", "", " ", "{x}", "Nan", "x"]


def make_folder(root: Path) -> Path:
    """A procedure folder with CSV profiles inside (one with nan), a file outside it, and links
    that lead out (``link.csv``, ``up/``) and in (``inlink.csv``)."""
    folder = root / "proc"
    (folder / "sub").mkdir(parents=True, exist_ok=True)
    (root / "outside.csv").write_text("t_s,a\n0,1\n1,2\n")
    (folder / "profile.csv").write_text("t_s,a\n0,0.5\n0.5,1.0\n1,0\n")
    (folder / "sub" / "x.csv").write_text("t_s,a\n0,0.2\n")
    (folder / "nan.csv").write_text("t_s,a\n0,1\n0.5,nan\n")
    (folder / "rows.csv").write_text("t_s,a\n" + "0,1\n" * (MAX_CSV_PROFILE_ROWS + 1))
    (folder / "huge.csv").write_text("t_s,a\n" + "0,1\n" * (MAX_CSV_PROFILE_BYTES // 4 + 1))
    for link, target in (
        ("link.csv", "../outside.csv"),
        ("up", ".."),
        ("inlink.csv", "profile.csv"),
    ):
        if not (folder / link).is_symlink():
            (folder / link).symlink_to(target)
    return folder


# --- the texts ------------------------------------------------------------------------------------


def _valid(p: StepParam) -> list[str]:
    """Values of a parameter that its checks accept, or nearly."""
    out: list[str] = []
    for v in (p.default, p.minimum, p.maximum):
        if isinstance(v, int | float) and not isinstance(v, bool):
            out.append(repr(v) if not isinstance(v, float) or math.isfinite(v) else "0")
    if p.choices:
        return out + [f"'{c}'" for c in p.choices]
    extra = {"vec3": ["[0, 0, 40]", "[1, 0, 0]", "[0, 0, 0]"], "range2": ["[10, 30]", "[0, 1000]"],
             "list_float": ["[0, 0.5, 1]", "[1]"], "list_str": ["[bus]", "[]", "[two lines]"],
             "dict": ["{bias_nt: 30, scale: 0.002}", "{scale: -1}"],
             "list_dict": ["[{result: a, value: b, max: 60}]", "[{result: a, value: b, min: '{x}'}]",
                           "[{result: a, value: b, max: .nan}]", "[{channel: bus, face: '-x', max_a: 1}]"],
             "str": ["'2019-12-09T12:00:00Z'", "dut", "'{x}'"]}  # fmt: skip
    return out + extra.get(p.kind, ["1", "2", "0.5"])


@st.composite
def _value(draw: st.DrawFn, p: StepParam | None, key: str = "") -> str:
    """A parameter's value as YAML text: one time in eight hostile, else (nearly) valid."""
    if draw(st.integers(0, 7)) == 5:  # not 0, which Hypothesis draws far more often
        return draw(st.sampled_from(HOSTILE))
    valid = _valid(p) if p is not None else ["1", "2.5", "SN-0001", "''"]
    return draw(st.sampled_from(valid + ([ISS_TLE] * 3 if key == "tle" else [])))


@st.composite
def _mapping(draw: st.DrawFn, params: dict[str, StepParam]) -> str:
    """A flow mapping of parameters: the required ones (usually), some others, rarely junk."""
    required = [k for k, p in params.items() if p.required]
    optional = [k for k, p in params.items() if not p.required]
    keys = [k for k in required if draw(st.integers(0, 9)) != 5]
    keys += draw(st.lists(st.sampled_from(optional), max_size=3, unique=True)) if optional else []
    keys += ["junk"] if draw(st.integers(0, 9)) == 5 else []
    return "{" + ", ".join(f"{k}: {draw(_value(params.get(k), k))}" for k in keys) + "}"


@st.composite
def _step(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from([*KINDS, "hodl"]))
    params = KINDS[kind].params if kind in KINDS else {}
    odd = draw(st.integers(0, 9)) == 5
    body = draw(st.sampled_from(["", "'mount {x}'", "[1]", "5"])) if odd else draw(_mapping(params))
    text = f"  - {kind}: {body}\n"
    if draw(st.booleans()) and (
        kind not in KINDS or KINDS[kind].takes_loads or draw(st.integers(0, 9)) == 5
    ):
        prof = draw(st.sampled_from([*LOAD_PROFILES, "csv", "csv", "sqaure"]))
        if prof == "csv":
            pbody = f"{{file: {draw(st.sampled_from(FILES))}, column: {draw(st.sampled_from(['a', 'b']))}}}"
        else:
            pbody = draw(
                st.one_of(_mapping(LOAD_PROFILES.get(prof, {})), st.sampled_from(["5", "[]"]))
            )
        ch = draw(st.sampled_from(["bus", "panel", "nope"]))
        text += f"    loads: {{{ch}: {{{prof}: {pbody}}}}}\n"
    if draw(st.integers(0, 4)) == 3:
        text += f"    name: {draw(st.sampled_from(['sweep', '{x}', '.nan', '[1]']))}\n"
    return text


def _bomb(levels: int) -> str:
    lines = ["      - &b0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"]
    lines += [f"      - &b{i} [{', '.join([f'*b{i - 1}'] * 9)}]\n" for i in range(1, levels + 1)]
    return "".join(lines)


BULK: dict[str, Callable[[], tuple[str, str]]] = {  # (parameter default block, more steps)
    "many steps": lambda: ("", "  - hold: {hold_s: 1}\n" * (MAX_STEPS + 1)),
    "twice the steps": lambda: ("", "  - report: {}\n" * (2 * MAX_STEPS)),
    "big file": lambda: ("", "# " + "x" * (1024 * 1024) + "\n"),
    "alias bomb": lambda: (_bomb(9), ""),
    "small alias chain": lambda: (_bomb(3), ""),
    "many aliases": lambda: ("      - &b0 1\n      - [" + ", ".join(["*b0"] * 150) + "]\n", ""),
    "deep": lambda: ("      - " + "[" * 100_000 + "]" * 100_000 + "\n", ""),
    "eight days": lambda: ("", "  - hold: {hold_s: 86400}\n" * 8),
    "load set-points": lambda: ("", "  - hold: {hold_s: 86400}\n    loads: {bus: {ramp: {to_a: 1, step_s: 0.02}}}\n"),
}  # fmt: skip


@dataclass
class Case:
    """One procedure text (or raw bytes) and its ``--set`` overrides."""

    data: bytes
    overrides: dict[str, str] = field(default_factory=dict)
    bulk: str = ""


@st.composite
def cases(draw: st.DrawFn) -> Case:
    """Procedure texts: mostly assembled from the vocabulary, some with bulk, edits or noise."""
    overrides = (
        draw(st.dictionaries(st.sampled_from(["x", "y", "w"]), st.sampled_from(OVERRIDES), max_size=2))
        if draw(st.integers(0, 3)) == 0
        else {}
    )  # fmt: skip
    shape = draw(st.sampled_from(["assembled"] * 6 + ["bulk", "edited", "text", "bytes"]))
    if shape == "text":
        return Case(draw(st.text(max_size=300)).encode("utf-8", "surrogatepass"), overrides)
    if shape == "bytes":
        return Case(draw(st.binary(max_size=300)), overrides)
    bulk = draw(st.sampled_from(sorted(BULK))) if shape == "bulk" else ""
    bomb, more = BULK[bulk]() if bulk else ("", "")
    text = (
        "procedure: fuzz\nparameters:\n"
        f"  x: {{default: {draw(_value(None))}}}\n"
        f"  y: {{default: {draw(_value(None))}, allow_empty: yes}}\n"
        + ("  z:\n    default:\n" + bomb if bomb else "")
        + f"magnetometers: {{dut: dut, reference: reference}}\nloads: {draw(st.sampled_from(['[bus, panel]'] * 6 + ['[bus]', '[]', '.nan']))}\n"
        + "steps:\n"
        + more  # first: the limit it reaches is what refuses it
        + "".join(draw(st.lists(_step(), min_size=draw(st.sampled_from([1] * 9 + [0])), max_size=5)))
    )  # fmt: skip
    if shape == "edited":
        at = draw(st.integers(0, len(text)))
        cut = draw(st.integers(0, 20))
        text = text[:at] + draw(st.text(max_size=8)) + text[at + cut :]
    return Case(text.encode("utf-8", "surrogatepass"), overrides, bulk)


# --- the property ---------------------------------------------------------------------------------


def _numbers(value: Any) -> list[float]:
    if isinstance(value, float | int) and not isinstance(value, bool):
        return [float(value)]
    if isinstance(value, dict):
        return [x for v in value.values() for x in _numbers(v)]
    if isinstance(value, list | tuple):
        return [x for v in value for x in _numbers(v)]
    return []


def category(exc: UserInputError) -> str:
    """What kind of refusal an error is (for the bench's table)."""
    msg = str(exc)
    if isinstance(exc, NotFiniteError):
        return "non-finite number"
    limit = re.search(r"\((MAX_[A-Z_]+)", msg)
    if limit:
        return f"limit {limit.group(1)}"
    for needle, name in (
        ("procedure's folder", "file outside the procedure's folder"),
        ("YAML syntax", "YAML syntax"),
        ("YAML value", "YAML value (tag, date, int)"),
        ("not UTF-8", "not UTF-8"),
        ("alias *", "alias loop"),
        ("placeholder", "placeholder"),
        ("format '{", "placeholder"),
        ("unknown parameter '{", "placeholder"),
        ("unknown step or key", "unknown step or key"),
        ("has no parameter", "unknown parameter"),
        ("must be within", "out of range"),
        ("must be at least", "out of range"),
        ("must be at most", "out of range"),
        ("load profile file", "load profile file"),
        ("load ", "load profile"),
        ("--set", "--set"),
        ("must be one of", "not one of the choices"),
        ("must be a", "wrong type"),
        ("must be [low, high]", "wrong type"),
        ("needs", "missing something"),
        ("exactly one", "missing something"),
    ):
        if needle in msg:
            return name
    return "other validation"


def check(folder: Path, case: Case) -> str:
    """Parse ``case`` in ``folder`` and compile its plan; ``"parsed"`` or the refusal's category.
    An AssertionError (or any other exception) breaks the property."""
    path = folder / "p.yaml"
    path.write_bytes(case.data)
    # this thread's CPU time, not the wall clock: a parse that hangs burns CPU, while one that
    # was only descheduled on a busy computer does not (a wall-clock bound failed beside CPU hogs)
    t0 = time.thread_time()
    try:
        proc = parse_procedure(path, case.overrides)
    except UserInputError as exc:
        msg = str(exc)
        assert "\n" not in msg and msg.startswith(str(path)), msg
        return category(exc)
    finally:
        took = time.thread_time() - t0
        assert took < PARSE_BOUND_S, f"parse took {took:.1f} s of CPU"
    assert 0 < len(proc.steps) <= MAX_STEPS
    durations = [step_duration(s) for s in proc.steps]
    assert all(math.isfinite(d) and d >= 0 for d in durations)
    assert sum(durations) <= MAX_TOTAL_DURATION_S
    for s in proc.steps:
        assert all(math.isfinite(x) for x in _numbers(s.params)), s
        for kind, params in s.loads.values():
            assert all(math.isfinite(x) for x in _numbers(params)), s
            if kind == "csv":
                assert (folder / params["file"]).resolve().is_relative_to(folder.resolve())
    cheap = sum(durations) <= 4 * 3600 and all(
        s.params.get("rate_hz", 0) * s.params.get("duration_s", 0) <= 20_000 for s in proc.steps
    )
    if not cheap:
        return "parsed, plan not compiled (long)"
    try:  # compile the plan: every command at a finite time with finite numbers
        for plan in compile_plan(proc):
            assert math.isfinite(plan.duration_s)
            for c in plan.commands:
                assert math.isfinite(c.t_s) and all(math.isfinite(x) for x in _numbers(c.payload))
    except UserInputError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(path)), str(exc)
        return "plan: " + category(exc)
    return "parsed, plan compiled"


def run(
    examples: int, folder: Path, seed_value: int | None = None, slowest: list[Any] | None = None
) -> Counter[str]:
    """The property over ``examples`` cases; the outcomes counted by category. ``slowest`` gets
    the longest example's (seconds, outcome, bulk)."""
    outcomes: Counter[str] = Counter()
    worst = slowest if slowest is not None else []

    @settings(max_examples=examples, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(cases())
    def prop(case: Case) -> None:
        t0 = time.monotonic()
        outcome = check(folder, case)
        took = time.monotonic() - t0
        outcomes[outcome] += 1
        if not worst or took > worst[0]:
            worst[:] = [took, outcome, case.bulk]
        if case.bulk:
            outcomes[f"(bulk: {case.bulk})"] += 1

    if seed_value is not None:
        prop = seed(seed_value)(prop)
    prop()
    return outcomes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="fuzz-procedures-") as tmp:
        folder = make_folder(Path(tmp))
        t0 = time.monotonic()
        slowest: list[Any] = []
        outcomes = run(args.examples, folder, args.seed, slowest)
        took = time.monotonic() - t0
    bulk = {k: v for k, v in outcomes.items() if k.startswith("(bulk")}
    plain = {k: v for k, v in outcomes.items() if k not in bulk}
    total = sum(plain.values())
    print(
        f"{total} examples in {took:.1f} s ({1000 * took / max(total, 1):.1f} ms each), seed {args.seed}"
    )
    parsed = {k: plain.pop(k) for k in list(plain) if k.startswith("parsed")}
    print(
        f"  parsed: {sum(parsed.values())} ({', '.join(f'{v} {k[8:]}' for k, v in parsed.items())})"
    )
    print(f"  refused: {sum(plain.values())}, by category:")
    for name, n in sorted(plain.items(), key=lambda kv: -kv[1]):
        print(f"    {n:6d}  {name}")
    print("  bulk cases generated (each refused by its limit unless an edit broke it first):")
    for name, n in sorted(bulk.items(), key=lambda kv: -kv[1]):
        print(f"    {n:6d}  {name[7:-1]}")
    print(f"no other exception; slowest example {slowest[0]:.2f} s ({slowest[1]}"
          f"{', bulk: ' + slowest[2] if slowest[2] else ''}), bound {PARSE_BOUND_S:g} s")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
