"""Build and check the SUMO networks with the netconvert shipped in the eclipse-sumo wheel.

A network is described by a netconvert configuration (``*.netccfg``) naming its
plain-XML sources (nodes, edges, types, connections, traffic lights). The built
``.net.xml`` is committed, so a fresh checkout runs without building;
``cosim nets check`` fails when a source changed after the build.

"Changed after the build" is decided by content, not file times: a build writes
``<net>.sources.sha256`` with the hash of each source (git sets every file's time
at checkout, so times cannot tell). Without that file, times are compared.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

from cosim.errors import NetError, SimulatorUnavailable
from cosim.scenario import nets_dir

SOURCE_KEYS = ("node-files", "edge-files", "type-files", "connection-files", "tllogic-files")


def default_configs() -> list[Path]:
    """Every netconvert configuration under the bundled sumo_nets folder."""
    return sorted(nets_dir().glob("*/*.netccfg"))


def netconvert_binary() -> Path:
    """The netconvert of the eclipse-sumo wheel (no SUMO_HOME or system install needed)."""
    try:
        import sumo
    except ImportError as exc:
        raise SimulatorUnavailable(
            "the eclipse-sumo package is missing; install it with `pip install eclipse-sumo==1.28.0`"
        ) from exc
    binary = Path(sumo.__file__).parent / "bin" / "netconvert"
    if not binary.exists():
        raise SimulatorUnavailable(f"netconvert not found at {binary}; reinstall eclipse-sumo")
    return binary


def _read_config(cfg: Path) -> tuple[list[Path], Path]:
    if not Path(cfg).is_file():
        raise NetError(f"netconvert configuration {cfg} does not exist; pass an existing .netccfg "
                       "to --config (or none for the bundled networks)")
    try:
        root = ET.parse(cfg).getroot()
    except ET.ParseError as exc:
        raise NetError(f"{cfg}: malformed netconvert configuration: {exc}") from exc
    sources: list[Path] = []
    output = None
    for el in root.iter():
        value = el.get("value")
        if value is None:
            continue
        if el.tag in SOURCE_KEYS:
            sources += [cfg.parent / v.strip() for v in value.split(",") if v.strip()]
        elif el.tag == "output-file":
            output = cfg.parent / value
    if output is None:
        raise NetError(f"{cfg}: no <output-file> in the configuration")
    return sources, output


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _manifest(output: Path) -> Path:
    return output.with_name(output.name + ".sources.sha256")


def stale(cfg: Path) -> list[Path]:
    """Sources of `cfg` changed since its network was built (all of them if it is missing)."""
    sources, output = _read_config(cfg)
    missing = [s for s in sources if not s.exists()]
    if missing:
        raise NetError(f"{cfg}: source file(s) missing: {', '.join(map(str, missing))}")
    if not output.exists():
        return sources
    manifest = _manifest(output)
    if manifest.exists():
        recorded = dict(
            reversed(line.split(maxsplit=1)) for line in manifest.read_text().splitlines() if line
        )
        return [s for s in sources + [cfg] if recorded.get(s.name) != _digest(s)]
    built = output.stat().st_mtime
    return [s for s in sources if s.stat().st_mtime > built]


def check(configs: list[Path] | None = None) -> None:
    """Raise NetError naming every network whose sources are newer than its build."""
    problems = []
    for cfg in configs or default_configs():
        newer = stale(cfg)
        if newer:
            _, output = _read_config(cfg)
            problems.append(
                f"{output} is out of date: {', '.join(p.name for p in newer)} changed since it "
                "was built; run `cosim nets build`"
            )
    if problems:
        raise NetError("; ".join(problems))


def build(cfg: Path) -> Path:
    """Run netconvert on one configuration; return the built network's path."""
    _, output = _read_config(cfg)
    env = dict(os.environ)
    try:
        import sumo

        env.setdefault("SUMO_HOME", sumo.SUMO_HOME)
    except ImportError:
        pass
    proc = subprocess.run(
        [str(netconvert_binary()), "-c", cfg.name],
        cwd=cfg.parent, capture_output=True, text=True, env=env, check=False,
    )
    if proc.returncode != 0:
        msg = "\n".join(line for line in proc.stderr.splitlines() if "Error" in line) or proc.stderr
        raise NetError(f"netconvert failed on {cfg}: {msg.strip()}")
    sources, _ = _read_config(cfg)
    _manifest(output).write_text(
        "".join(f"{_digest(s)}  {s.name}\n" for s in sources + [cfg])
    )
    return output
