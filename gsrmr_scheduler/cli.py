"""``gsrmr-schedule``: solve a P_GS instance from JSON, or write a paper-default instance (``make-problem``).

Usage, input and output keys, and the one-line errors (exit code 2): docs/scheduling.md, "CLI"; ``--help``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any, NoReturn

import numpy as np

from gsrmr_common.channel import ChannelModel, paper_route_distances
from gsrmr_scheduler.problem import Problem, ProblemError
from gsrmr_scheduler.solve import METHODS, solve

PROG = "gsrmr-schedule"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2
        _fail(message)


def _fail(message: str) -> NoReturn:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _write(obj: dict[str, Any], out: str | None) -> None:
    text = json.dumps(obj, indent=1, allow_nan=False)
    if out:
        with open(out, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")
    else:
        print(text)


def make_problem(slots: int, seed: int, loss_threshold: float = 0.03, loss_max: float = 0.096) -> Problem:
    """Paper-default instance: τ = 0.1 s, I = 67.2 kbit, S = 192 bit, B = 1 MHz, σ² = −60 dBm, Rician
    channel along a 1.5 m circle 10 m from the server; GS losses ``L_t ~ U(0, loss_max)`` (mean 0.048 by
    default, the paper's all-GS loss)."""
    rng = np.random.default_rng(seed)
    gains = ChannelModel(seed=seed).gains(paper_route_distances(slots))
    losses = rng.uniform(0.0, loss_max, slots)
    return Problem(channel_gain=gains, gs_loss=losses, loss_threshold=loss_threshold)


def _make_main(argv: list[str]) -> int:
    ap = _Parser(prog=f"{PROG} make-problem", description="Write a paper-default P_GS instance as JSON.")
    ap.add_argument("--slots", type=int, required=True, help="number of slots T (>= 1)")
    ap.add_argument("--seed", type=int, required=True, help="seed of the channel and loss draws")
    ap.add_argument("--loss-threshold", type=float, default=0.03, help="L_th (default 0.03)")
    ap.add_argument("--loss-max", type=float, default=0.096, help="GS losses ~ U(0, loss-max) (default 0.096)")
    ap.add_argument("-o", "--output", help="output JSON (default: stdout)")
    args = ap.parse_args(argv)
    if args.slots < 1:
        _fail("--slots must be >= 1")
    if not (math.isfinite(args.loss_max) and args.loss_max >= 0):
        _fail("--loss-max must be a finite number >= 0")
    try:
        prob = make_problem(args.slots, args.seed, args.loss_threshold, args.loss_max)
    except ProblemError as exc:
        _fail(str(exc))
    _write(prob.to_dict(), args.output)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "make-problem":
        return _make_main(argv[1:])
    ap = _Parser(prog=PROG, description="Solve the GSCLO problem P_GS (see docs/scheduling.md). "
                 "Use 'make-problem' to write an instance.")
    ap.add_argument("problem", help="problem JSON file ('-' for stdin)")
    ap.add_argument("--method", required=True, help=f"one of: {', '.join(METHODS)}")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="method option (value parsed as JSON if possible), e.g. iterations=10, time_limit_s=0.5")
    ap.add_argument("-o", "--output", help="output JSON (default: stdout)")
    args = ap.parse_args(argv)
    if args.method not in METHODS:
        _fail(f"method: unknown method {args.method!r} (choose one of {', '.join(METHODS)})")
    options: dict[str, Any] = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or not key:
            _fail(f"option: expected KEY=VALUE, got {item!r}")
        options[key.strip()] = _parse_value(value)
    try:
        if args.problem == "-":
            data = json.load(sys.stdin)
        else:
            with open(args.problem, encoding="utf-8") as fh:
                data = json.load(fh, parse_constant=lambda c: float(c))
    except OSError as exc:
        _fail(f"problem: cannot read {args.problem!r}: {exc.strerror}")
    except json.JSONDecodeError as exc:
        _fail(f"problem: not valid JSON ({exc.msg} at line {exc.lineno})")
    try:
        prob = Problem.from_dict(data)
    except ProblemError as exc:
        _fail(f"field {exc}")
    try:
        sched = solve(prob, args.method, **options)
    except (ValueError, TypeError) as exc:
        _fail(f"option: {exc}")
    _write(sched.to_json(), args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
