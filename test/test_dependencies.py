"""Every module and every ``dea-twin`` sub-command works with only the declared dependencies.

What a plain ``pip install .`` (plus the ROS wheels of ``requirements-ros.txt``, or a ROS
install with package.xml's dependencies) provides is the closure of ``install_requires``
and the ROS wheels over their own requirements.  Instead of building such a venv (a
minute and 300 MB per run), a subprocess of this interpreter hides every other installed
distribution (``sys.modules[name] = None``: ``import`` fails and
``importlib.util.find_spec`` answers None, exactly as if it were not installed), then
imports every module of the package and asks every sub-command for ``--help``.  The
optional extras (matplotlib, Dask) must then fail with a message naming the extra.
"""

import importlib.metadata as md
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirements(dist: md.Distribution, extras: tuple[str, ...] = ()) -> list[tuple[str, tuple[str, ...]]]:
    """(name, extras) of what ``dist`` requires, without other extras' requirements."""
    out = []
    for text in dist.requires or []:
        requirement, _, marker = text.partition(";")
        extra = re.search(r"extra\s*==\s*['\"]([^'\"]+)", marker)
        if extra and extra.group(1) not in extras:
            continue
        match = re.match(r"\s*([A-Za-z0-9._-]+)\s*(?:\[([^\]]*)\])?", requirement)
        wanted = tuple(e.strip() for e in (match.group(2) or "").split(",") if e.strip())
        out.append((_norm(match.group(1)), wanted))
    return out


def undeclared_modules() -> list[str]:
    """Top-level modules installed here that neither the declared dependencies nor their requirements provide."""
    dists = {}
    for dist in md.distributions():
        dists.setdefault(_norm(dist.metadata["Name"]), dist)
    ours = dists["dea-array-twin"]
    roots = [(_norm(line.strip()), ()) for line in (REPO / "requirements-ros.txt").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    roots += _requirements(ours)
    allowed, todo = {"dea-array-twin"}, list(roots)
    seen = set()
    while todo:
        name, extras = todo.pop()
        if (name, extras) in seen or name not in dists:
            continue
        seen.add((name, extras))
        allowed.add(name)
        todo += _requirements(dists[name], extras)
    return sorted(module for module, owners in md.packages_distributions().items()
                  if not any(_norm(owner) in allowed for owner in owners))


CHECK = textwrap.dedent("""
    import contextlib, importlib, io, json, pkgutil, sys
    for name in json.loads(sys.argv[1]):
        sys.modules[name] = None
    import dea_array_twin
    failed = {}
    for info in pkgutil.walk_packages(dea_array_twin.__path__, "dea_array_twin."):
        if info.name.endswith(".__main__"):  # runs the command line when imported
            continue
        try:
            importlib.import_module(info.name)
        except Exception as exc:
            failed[info.name] = repr(exc)
    from dea_array_twin.cli.main import build_parser, main
    commands = [a for a in build_parser()._subparsers._group_actions[0].choices]
    codes = {}
    for argv in [["--version"], ["--help"]] + [[c, "--help"] for c in commands]:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            try:
                codes[" ".join(argv)] = main(argv)
            except SystemExit as exc:
                codes[" ".join(argv)] = exc.code
    extras = {}
    for argv in (["plot", "x.mcap"], ["study", "coupling"], ["calibrate", "x.csv"]):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            extras[argv[0]] = [main(argv), err.getvalue()]
    from dea_array_twin.parallel import ExecutorError, run_tasks
    try:
        run_tasks(len, [], scheduler="tcp://127.0.0.1:9")
    except ExecutorError as exc:
        extras["--scheduler"] = [2, str(exc)]
    print(json.dumps({"failed": failed, "commands": commands, "codes": codes, "extras": extras}))
""")


@pytest.fixture(scope="module")
def bare_install():
    """What the subprocess with only the declared dependencies found."""
    try:
        md.distribution("dea_array_twin")
    except md.PackageNotFoundError:
        pytest.skip("dea_array_twin is not installed (run tools/setup.sh): its declared requirements are unknown")
    hidden = undeclared_modules()
    proc = subprocess.run([sys.executable, "-c", CHECK, json.dumps(hidden)], cwd=REPO, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return hidden, json.loads(proc.stdout.splitlines()[-1])


def test_the_optional_extras_are_hidden_and_the_core_ones_are_not(bare_install):
    hidden, _ = bare_install
    assert {"matplotlib", "dask", "distributed", "rosbags", "pytest"} <= set(hidden)
    assert not {"mcap", "mcap_ros2", "numpy", "scipy", "gmsh", "yaml", "tqdm", "rclpy", "std_msgs"} & set(hidden)


def test_every_module_imports_with_only_the_declared_dependencies(bare_install):
    _, found = bare_install
    assert found["failed"] == {}


def test_every_sub_command_answers_help_and_version(bare_install):
    _, found = bare_install
    assert {"curve", "solve", "run", "demo", "replay", "plot", "study", "calibrate", "bag-recover"} <= \
        set(found["commands"])
    assert set(found["codes"].values()) == {0}, found["codes"]


def test_a_missing_extra_is_named_not_a_traceback(bare_install):
    _, found = bare_install
    for command in ("plot", "study", "calibrate"):
        code, err = found["extras"][command]
        assert code == 2 and "dea_array_twin[plot]" in err and "Traceback" not in err, (command, err)
    assert "[cluster]" in found["extras"]["--scheduler"][1]
