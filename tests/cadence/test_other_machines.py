"""The same story on every machine (issue 53). This machine plays others: numpy with its AVX-512 kernels
off, with its AVX2 kernels off too, and OpenBLAS with the kernels of two other core families (one of them
on one thread). A simulated study and the lockstep demo give the same story under each, byte for byte:
the windows, selections, cycles and errors, and the study's tables. Each run's recorded build shows that
the setting took effect (another SIMD set, another BLAS core), so a pass is not a run that changed
nothing. What this machine cannot play (no AVX-512 to switch off, say) is said in a warning."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest

from cadence.tools.recording import read
from common.runtime.resources import SHIPPED_SETS
from common.trajectory.shipped import read_shipped

STORY = ("windows", "selections", "cycle_ends_s", "cycle_times_s", "error_times_s", "events", "cycles")


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    return {
        f for line in text.splitlines() if line.startswith(("flags", "Features")) for f in line.split()[2:]
    }


def _build(env: dict[str, str]) -> str:
    """What numpy and the BLAS compute with under ``env`` (common/runtime/numeric.py), in a fresh process."""
    code = "from common.runtime.numeric import numeric_build; print(numeric_build())"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=os.environ | env)  # fmt: skip
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def machines() -> dict[str, dict[str, str]]:
    """The settings that make this machine compute as another would, by name; each is kept only when it
    changes the build (a setting this process already runs under, or kernels the CPU lacks, would play
    this machine again), and those it cannot play are said in a warning."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    on = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]  # what numpy uses here and now
    flags = _cpu_flags()
    wanted: dict[str, dict[str, str]] = {}
    blas: list[tuple[str, str, bool]]  # (name, core type, the CPU can run it)
    if platform.machine() in ("x86_64", "AMD64"):
        # every such name numpy dispatches to, in use or not: the setting replaces one this process runs under
        avx512 = [f for f in __cpu_dispatch__ if "AVX512" in f or f == "X86_V4"]
        avx2 = avx512 + [f for f in __cpu_dispatch__ if f in ("X86_V3", "AVX2", "FMA3", "F16C")]
        wanted["numpy without AVX-512"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(avx512)}
        wanted["numpy without AVX2"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(avx2)}
        blas = [
            ("Prescott", "Prescott", True),
            ("SkylakeX", "SkylakeX", "avx512f" in flags),
            ("Haswell", "Haswell", "avx2" in flags),
            ("Sandybridge", "Sandybridge", "avx" in flags),
        ]
    else:  # aarch64: numpy's dispatched extensions off, and OpenBLAS's generic and Neoverse kernels
        wanted["numpy baseline only"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(on)}
        blas = [("ARMV8", "ARMV8", True), ("NeoverseN1", "NEOVERSEN1", "asimddp" in flags)]
    base = _build({})
    plays: dict[str, dict[str, str]] = {"as it is": {}}
    cannot = []
    for name, env in wanted.items():
        if any(f in on for f in env["NPY_DISABLE_CPU_FEATURES"].split()) and _build(env) != base:
            plays[name] = env
        else:
            cannot.append(f"{name}: numpy here has none of those kernels in use ('as it is' plays it)")
    families = 0
    for name, core, runs in blas:  # two families of OpenBLAS kernels other than this machine's
        env = {"OPENBLAS_CORETYPE": core} | ({"OPENBLAS_NUM_THREADS": "1"} if families == 0 else {})
        if families < 2 and runs and _build(env) != base:
            plays[f"OpenBLAS {name}" + (", one thread" if families == 0 else "")] = env
            families += 1
    if families < 2:
        cannot.append(f"OpenBLAS: {families} family of kernels other than this machine's, not 2")
    if cannot:
        warnings.warn("could not play: " + "; ".join(cannot), stacklevel=2)
    return plays


def _run(args: list[str], env: dict[str, str]) -> None:
    r = subprocess.run([sys.executable, "-m", "cadence", *args], capture_output=True, text=True, timeout=600,
                       env=os.environ | env)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr


def _study_story(out: Path) -> tuple[str, str, list[str]]:
    """The digest of a study's story: every session file's messages (key, data time, bytes; not the
    metadata, which names the build) and the analysis's tables. Then its build, and its sets."""
    sha = hashlib.sha256()
    for f in sorted((out / "sessions").glob("*.mcap")):
        for rec in read(f):
            sha.update(rec.key.encode() + rec.log_time.to_bytes(8, "little") + rec.data)
    doc = json.loads((out / "study.json").read_text())
    for part in ("table", "friedman", "wilcoxon", "equivalence_b_c"):
        sha.update(json.dumps(doc[part], sort_keys=True).encode())
    (build,) = doc["builds"]
    return sha.hexdigest(), build, doc["sets_sha256"]


def _demo_story(out: Path) -> tuple[str, str, list[str]]:
    s = json.loads((out / "summary.json").read_text())
    story = json.dumps({k: s[k] for k in STORY}, sort_keys=True).encode()
    return hashlib.sha256(story).hexdigest(), s["build"], [s["sets_sha256"]]


@pytest.mark.parametrize(
    ("what", "args", "story"),
    [
        (
            "study",
            ["study", "simulate", "--subjects", "4", "--minutes", "4", "--calibrate", "2"],
            _study_story,
        ),
        ("demo", ["demo", "--speed", "max", "--duration", "150", "--no-live"], _demo_story),
    ],
)
def test_the_same_story_whatever_kernels_numpy_and_the_blas_pick(
    tmp_path: Path, what: str, args: list[str], story: Callable[[Path], tuple[str, str, list[str]]]
) -> None:
    plays = machines()
    shipped = read_shipped(SHIPPED_SETS / "box_filling.json").sets_sha256
    told = {}
    for name, env in plays.items():
        out = tmp_path / name.replace(" ", "_").replace(",", "")
        _run([*args, "--out", str(out)], env)
        told[name] = story(out)
    base_story, base_build, _ = told["as it is"]
    for name, (digest, build, sets) in told.items():
        assert sets == [shipped], f"{what}, {name}: ran on sets {sets}, not the shipped {shipped[:12]}"
        assert digest == base_story, f"{what}, {name} ({build}): another story than as it is ({base_build})"
        if name != "as it is":  # the setting took effect: numpy or the BLAS computed with other kernels
            assert build != base_build, f"{what}, {name}: the build is still {build}"
