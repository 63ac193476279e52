"""A scenario's YAML (bundled, or any file) copied anywhere, its file paths made absolute, with
top-level keys changed: the starting point of a pilot on a variant of the task.

    python studies/scenario_copy.py env_3 pilots/env_3_solid.yaml --set solid_cars=true
    cosim train --algo dqn --env pilots/env_3_solid.yaml --preset standard --out pilots/solid

Values are read as YAML (``true``, ``600``, ``{scale: 0.5}``); the copy is loaded once before
it is kept, so a bad key or value is refused with cosim's own message (docs/task.md, "Solid cars").
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from cosim.errors import ScenarioError
from cosim.scenario import load_scenario, scenario_data


def copy_scenario(name: str, out: Path, changes: dict) -> Path:
    """Write scenario ``name`` (bundled, or a YAML's path) to ``out`` with absolute paths and
    ``changes`` applied."""
    try:
        data = scenario_data(name)
    except ScenarioError as exc:
        raise SystemExit(f"scenario_copy: {exc}") from None
    data.update(changes)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.yaml")
    tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    try:
        load_scenario(tmp)
    except ScenarioError as exc:
        tmp.unlink()
        raise SystemExit(f"scenario_copy: {exc}") from None
    tmp.replace(out)
    return out


def _change(text: str) -> tuple[str, object]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"--set {text!r}: write KEY=VALUE, e.g. solid_cars=true")
    return key, yaml.safe_load(value)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", help="a bundled scenario (env_1 .. env_5) or a scenario YAML")
    p.add_argument("out", type=Path, help="the copy's path (.yaml)")
    p.add_argument("--set", type=_change, action="append", default=[], metavar="KEY=VALUE",
                   help="a top-level scenario key and its YAML value (repeatable)")
    args = p.parse_args(argv)
    print(copy_scenario(args.scenario, args.out, dict(args.set)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
