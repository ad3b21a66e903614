"""deliffas.engine.devices.cpu_threads: the training process's intra-op threads."""

import os

from deliffas.engine.devices import cpu_threads


def test_cpu_threads_keeps_omp_num_threads_as_a_cap(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert cpu_threads() == 8
    assert cpu_threads(ranks=2, workers=1) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # runs started side by side, one thread each
    assert cpu_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "16")  # never more than the cores left
    assert cpu_threads(ranks=2) == 4
    monkeypatch.setenv("OMP_NUM_THREADS", "many")  # not a count: ignored
    assert cpu_threads() == 8
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    assert cpu_threads(workers=1) == 1
