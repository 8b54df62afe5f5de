"""The built wheel works on its own: installed in a fresh venv and run from a folder outside the repository,
``seqtrojan train --config NAME`` and ``seqtrojan reproduce`` find the shipped presets.

Offline and without downloading torch: the wheel is built with the current venv's setuptools (no build
isolation) and installed with ``--no-deps --no-index``; the fresh venv sees the current venv's site-packages
(torch and the other dependencies) through a plain path in a .pth file, which does not run the editable install's
hook, so ``seqtrojan`` itself can only come from the wheel (checked).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT
from tests.experiments.test_reproduce import TINY

pytestmark = pytest.mark.slow


def run(*args, cwd: Path, timeout: int = 900) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(OMP_NUM_THREADS="1", PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    out = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, f"{args}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """(the fresh venv's bin folder, an empty working folder outside the repository)."""
    tmp = tmp_path_factory.mktemp("packaging")
    src = tmp / "src"  # only what the build reads: no configs/, no tests, no build/ or egg-info of the checkout
    shutil.copytree(ROOT / "seqtrojan", src / "seqtrojan", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    run(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", tmp / "dist",
        src, cwd=tmp)  # fmt: skip
    (wheel,) = (tmp / "dist").glob("seqtrojan-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "seqtrojan/presets/clean_7x7.yaml" in names and "seqtrojan/presets/reproduce_smoke.yaml" in names
    kernels = {f"seqtrojan/agent/csrc/{p.name}" for p in (ROOT / "seqtrojan" / "agent" / "csrc").iterdir()}
    assert kernels and kernels <= set(names), kernels - set(names)  # every kernel source and header ships

    venv = tmp / "venv"
    run(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp)
    python = venv / "bin" / "python"
    purelib = Path(
        run(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])", cwd=tmp).stdout.strip()
    )
    (purelib / "_reuse_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    run(sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", wheel, cwd=tmp)
    work = tmp / "work"
    work.mkdir()
    where = run(python, "-c", "import seqtrojan; print(seqtrojan.__file__)", cwd=work).stdout.strip()
    assert Path(where).is_relative_to(purelib), where  # the wheel's copy, not the checkout
    return venv / "bin", work


def test_train_finds_a_preset_by_name_outside_the_repository(installed):
    bin_dir, work = installed
    run(bin_dir / "seqtrojan", "train", "--config", "clean_7x7", "--ppo.total-steps", "16384", "--ppo.num-envs", "64",
        "--run.out-dir", "runs", "--run.name", "r", "--run.eval-episodes", "32", "--run.no-progress",
        "--run.lstm-backend", "torch", cwd=work)  # fmt: skip
    card = json.loads((work / "runs" / "r" / "model" / "card.json").read_text())
    assert card["env_steps"] == 16384
    assert [s["size"] for s in card["config"]["curriculum"]["stages"]] == [5, 5, 7]  # clean_7x7's curriculum


def test_reproduce_finds_its_scales_and_presets_outside_the_repository(installed):
    bin_dir, work = installed
    assert "--scale" in run(bin_dir / "seqtrojan", "reproduce", "--help", cwd=work).stdout
    check = (
        "from seqtrojan.experiments.reproduce import load_reproduce_config\n"
        "from seqtrojan.experiments.specs import experiment_from_spec\n"
        "for scale in ('smoke', 'paper'):\n"
        "    c = load_reproduce_config(scale)\n"
        "    for role, spec in (('clean', c.clean), ('backdoor', c.backdoor)):\n"
        "        experiment_from_spec(spec, 'runs', role, 'cpu')\n"
    )
    run(bin_dir / "python", "-c", check, cwd=work)
    # a tiny scale file (the end-to-end test's) whose agents name shipped presets, run through to the report
    (work / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    run(bin_dir / "seqtrojan", "reproduce", "--scale", "tiny.yaml", "--out", "results", cwd=work)
    assert (work / "results" / "report.html").stat().st_size > 10_000
