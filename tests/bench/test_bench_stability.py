"""`omnisplat-bench stability --short --json`: every stiff/extreme case passes on a small model."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

from bench import stability as bench_stability  # noqa: E402

SHORT_CASES = [name for name, _ in bench_stability.cases(short=True)]

#: Known failures, each a finding for another module's owner. strict: when fixed, the XPASS fails the
#: run so the mark gets removed.
KNOWN: dict[str, str] = {}  # case name -> reason (none at the moment)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    models = tmp_path_factory.getbasetemp() / "bench_models"  # shared with test_bench_quality
    models.mkdir(exist_ok=True)
    out = tmp_path_factory.mktemp("stability")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = bench_stability.main(["--short", "--json", "--out", str(out), "--models-dir", str(models)])
    lines = [line for line in buf.getvalue().splitlines() if line.strip()]
    assert len(lines) == 1, "--json must print exactly one JSON object"
    data = json.loads(lines[0])
    data["_rc"] = rc
    return data


def test_report_shape(report):
    assert [c["name"] for c in report["cases"]] == SHORT_CASES
    assert report["passed"] + report["failed"] == len(SHORT_CASES)
    assert report["passed"] == sum(c["passed"] for c in report["cases"])
    assert report["_rc"] == (0 if report["failed"] == 0 else 1)
    for case in report["cases"]:
        assert (Path(report["out_dir"]) / case["figure"]).read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(strict=True, reason=KNOWN[n])) if n in KNOWN else n for n in SHORT_CASES])
def test_case_passes(report, name):
    case = next(c for c in report["cases"] if c["name"] == name)
    assert case["passed"], f"{name}: {case['criterion']} -- {case['detail']}"
