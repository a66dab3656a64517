"""The benchmark suite's timing helper (`benchmarks/_common.py`), on fake workloads."""

import importlib.util
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("_bench_common", ROOT / "benchmarks" / "_common.py")
common = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(common)


def paths_cold_after_a_switch(cold=0.02, warm=0.001):
    """Two callables that each take `cold` seconds on the first call after the other one ran
    (caches and threads taken over by another path) and `warm` seconds after that."""
    last = [None]

    def path(name):
        def call():
            time.sleep(cold if last[0] != name else warm)
            last[0] = name

        return call

    return {"a": path("a"), "b": path("b")}


def test_measure_times_warm_calls_after_an_untimed_warmup():
    # blocks of 10 ms, and blocks of one call each
    for min_time in (0.03, 0.0):
        stats = common.measure(paths_cold_after_a_switch(), min_time=min_time, rounds=3)
        for name, st in stats.items():
            assert st["median"] < 0.005, name  # the warm 1 ms calls, not the cold 20 ms one
            assert st["repeats"] >= 3
    # without the warm-up every block's first (and here only) call is a cold one
    cold = common.measure(paths_cold_after_a_switch(), min_time=0.03, rounds=3, warmup=0.0)
    assert all(st["median"] >= 0.015 for st in cold.values())


def test_profile_dlt_attributes_the_kernels_to_the_dlt_stages(capsys):
    sys.path.insert(0, str(ROOT))
    try:
        from benchmarks import profile_dlt
    finally:
        sys.path.remove(str(ROOT))
    assert profile_dlt.stage_of("jit(f)/jit(solve_validated)/eigen/while/body/mul") == "eigen"
    assert profile_dlt.stage_of("jit(f)/jit(_decompose)/vmap()/dot_general") == "decompose"
    assert profile_dlt.stage_of("jit(f)/broadcast_in_dim") == "other"
    profile_dlt.main(["--cameras", "64", "--calls", "2"])
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines() if line}
    for stage in ("moments", "eigen", "cameras", "decompose"):
        assert float(rows[stage][1]) > 0, stage  # µs per camera
        assert int(rows[stage][3]) > 0, stage  # kernels per call
