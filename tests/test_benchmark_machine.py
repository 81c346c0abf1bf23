"""bench-scale names the CPU its ratios were measured on (benchmarks.scale_refs.cpu_description):
(b) and the compiled kernels gain unequally from wider vectors, so a ratio without its CPU
cannot be compared with another run's."""

from __future__ import annotations

import os
from pathlib import Path

from benchmarks.scale_refs import cpu_description

CPUINFO = """processor	: {n}
vendor_id	: GenuineIntel
model name	: {model}
flags		: fpu sse2 {flags} fma
"""


def _cpuinfo(tmp_path: Path, flags: str) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text("\n".join(CPUINFO.format(n=n, model="Xeon X", flags=flags) for n in (0, 1)))
    return path


def test_the_description_names_the_model_the_cores_and_the_widest_vectors(tmp_path) -> None:
    cores = os.cpu_count() or 1
    assert cpu_description(_cpuinfo(tmp_path, "avx avx2 avx512f avx512bw")) == (
        f"Xeon X, {cores} cores, AVX-512"
    )
    assert cpu_description(_cpuinfo(tmp_path, "avx avx2")) == f"Xeon X, {cores} cores, AVX2"
    assert cpu_description(_cpuinfo(tmp_path, "avx")) == f"Xeon X, {cores} cores, no AVX2"


def test_an_unreadable_cpuinfo_still_gives_a_description(tmp_path) -> None:
    cores = os.cpu_count() or 1
    assert cpu_description(tmp_path / "absent") == f"unknown CPU, {cores} cores, no AVX2"
