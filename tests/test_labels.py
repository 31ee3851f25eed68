"""The one definition of the workbench's labels (cosim/base/labels.py): periods in file names, in prose and in the
benchmark table's ASCII row names, and the names derived from them."""

from __future__ import annotations

import pytest

from cosim.base.labels import did_you_mean, period_label, period_text, slug
from cosim.design.vocabulary import NNPC, PAPER_PERIOD, SWITCHING_PERIOD
from cosim.study.targets import controller_compute_benchmark


@pytest.mark.parametrize("period, label, text, ascii_text", [
    (PAPER_PERIOD, "1ms", "1 ms", "1 ms"),
    (2.5e-3, "2500us", "2.5 ms", "2.5 ms"),  # not a whole number of ms: the file label in us
    (SWITCHING_PERIOD, "13p33us", "13.33 µs", "13.33 us"),
    (10e-6, "10us", "10 µs", "10 us"),
])
def test_a_period_has_one_file_label_one_text_and_its_ascii_form(period, label, text, ascii_text):
    assert period_label(period) == label
    assert period_text(period) == text
    assert period_text(period, ascii_only=True) == ascii_text
    assert period_text(period, ascii_only=True).isascii()


def test_the_compute_target_row_is_named_as_the_benchmark_writes_its_rates():
    assert controller_compute_benchmark(NNPC, PAPER_PERIOD, "c") == "controller compute per step, NNPC, 1 ms, C twin"
    assert controller_compute_benchmark(NNPC, SWITCHING_PERIOD, "python") == \
        "controller compute per step, NNPC, 13.33 us, Python reference"


def test_slug_and_did_you_mean():
    assert slug("MPC-oracle (sync. sample)") == "mpc-oracle-sync-sample"
    assert did_you_mean("nnpcc", ["PI", "NNPC"]) == " (did you mean 'NNPC'?)"
    assert did_you_mean("zzz", ["a", "b"], hint_all=3) == " (expected one of a, b)"
    assert did_you_mean("zzz", ["a", "b"]) == ""
