"""The same story on every machine (issue 53). This machine plays others: numpy with its AVX-512 kernels
off, with its AVX2 kernels off too, and OpenBLAS with the kernels of two other core families (one of them
on one thread). A simulated study and the lockstep demo give the same story under each, byte for byte:
the windows, selections, cycles and errors, and the study's tables. Each run's recorded build shows that
the setting took effect (another SIMD set, another BLAS core), so a pass is not a run that changed
nothing. What this machine cannot play (no AVX-512 to switch off, say) is said in a warning."""

from __future__ import annotations

import hashlib
import json
import platform
import subprocess
import sys
import warnings
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


def machines() -> tuple[dict[str, dict[str, str]], list[str]]:
    """The settings that make this machine compute as another would, by name, and those it cannot play
    (with why)."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    on = [f for f in __cpu_dispatch__ if __cpu_features__.get(f)]
    flags = _cpu_flags()
    plays: dict[str, dict[str, str]] = {"as it is": {}}
    cannot = []
    if platform.machine() in ("x86_64", "AMD64"):
        avx512 = [f for f in on if "AVX512" in f or f == "X86_V4"]
        avx2 = avx512 + [f for f in on if f in ("X86_V3", "AVX2", "FMA3", "F16C")]
        for name, off in (("numpy without AVX-512", avx512), ("numpy without AVX2", avx2)):
            if off:
                plays[name] = {"NPY_DISABLE_CPU_FEATURES": " ".join(off)}
            else:
                cannot.append(f"{name}: this CPU gives numpy none of those kernels ('as it is' plays it)")
        plays["OpenBLAS Prescott, one thread"] = {
            "OPENBLAS_CORETYPE": "Prescott",
            "OPENBLAS_NUM_THREADS": "1",
        }
        if "avx512f" in flags:
            plays["OpenBLAS SkylakeX"] = {"OPENBLAS_CORETYPE": "SkylakeX"}
        elif "avx2" in flags:
            plays["OpenBLAS Haswell"] = {"OPENBLAS_CORETYPE": "Haswell"}
        else:
            cannot.append("OpenBLAS SkylakeX or Haswell: this CPU has neither AVX-512 nor AVX2")
    else:  # aarch64: numpy's dispatched extensions off, and OpenBLAS's generic and Neoverse kernels
        if on:
            plays["numpy baseline only"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(on)}
        plays["OpenBLAS ARMV8, one thread"] = {"OPENBLAS_CORETYPE": "ARMV8", "OPENBLAS_NUM_THREADS": "1"}
        plays["OpenBLAS NeoverseN1"] = {"OPENBLAS_CORETYPE": "NEOVERSEN1"}
        cannot.append("x86-64's AVX-512 and AVX2 kernels: not on this processor")
    if cannot:
        warnings.warn("could not play: " + "; ".join(cannot), stacklevel=2)
    return plays, cannot


def _run(args: list[str], env: dict[str, str]) -> None:
    import os

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
    tmp_path: Path, what: str, args: list[str], story: object
) -> None:
    plays, _ = machines()
    shipped = read_shipped(SHIPPED_SETS / "box_filling.json").sets_sha256
    told = {}
    for name, env in plays.items():
        out = tmp_path / name.replace(" ", "_").replace(",", "")
        _run([*args, "--out", str(out)], env)
        told[name] = story(out)  # type: ignore[operator]
    base_story, base_build, _ = told["as it is"]
    for name, (digest, build, sets) in told.items():
        assert sets == [shipped], f"{what}, {name}: ran on sets {sets}, not the shipped {shipped[:12]}"
        assert digest == base_story, f"{what}, {name} ({build}): another story than as it is ({base_build})"
        if name != "as it is":  # the setting took effect: numpy or the BLAS computed with other kernels
            assert build != base_build, f"{what}, {name}: the build is still {build}"
