"""The Ray driver (b2dr_ref.ray_driver) on a local Ray cluster: 3 shards of `b2dr sim` merge to the single
run bit for bit (CLS and every scenario), and a shard killed on its first attempt is retried by Ray, resumes
(its finished scenario is not rerun) and the merge is still identical. Skips when ray is not installed
(tools/ensure-python.sh installs it) or the b2dr binary is not built."""
import os
import stat
import subprocess
import sys
import textwrap

import pytest

from scale_helpers import SIM_ARGS, b2dr_binary, deterministic, load

try:
    import ray
except ImportError as e:  # printed, and the tests skip
    print(f"SKIP test_ray_driver: ray is not importable ({e}); pip install ray", file=sys.stderr)
    pytestmark = pytest.mark.skip(reason=f"ray is not importable ({e}); pip install ray")
    ray = None

from b2dr_ref import ray_driver


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=3, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    exe = b2dr_binary()
    out = tmp_path_factory.mktemp("single")
    subprocess.run([exe, *SIM_ARGS, "--out", str(out)], check=True, capture_output=True)
    return load(out / "metrics.json")


def check_equal(single, merged):
    assert merged["cls"] == single["cls"]  # exact: same floats, same summation order
    assert len(merged["scenarios"]) == 6
    assert deterministic(merged) == deterministic(single)


def test_three_shards_merge_to_the_single_run(cluster, single, tmp_path):
    exe = b2dr_binary()
    lines = []
    merged = ray_driver.run(SIM_ARGS, 3, tmp_path, b2dr=exe, num_cpus=1, progress=lines.append)
    check_equal(single, merged)
    assert sum("done" in m for m in lines) == 3, lines
    assert load(tmp_path / "merged" / "metrics.json") == merged
    for k in range(3):
        assert load(tmp_path / f"shard-{k}" / "config.json")["shard"] == {"index": k, "count": 3}


def test_a_killed_shard_is_retried_resumes_and_merges_the_same(cluster, single, tmp_path):
    exe = b2dr_binary()
    marker = tmp_path / "killed-once"
    # a b2dr that, on the first attempt of shard 1/3, is killed (SIGKILL) once its first scenario is done
    wrapper = tmp_path / "b2dr-flaky"
    wrapper.write_text(textwrap.dedent(f"""\
        #!{sys.executable}
        import glob, os, subprocess, sys, time
        args = sys.argv[1:]
        if "1/3" in args and not os.path.exists({str(marker)!r}):
            out = args[args.index("--out") + 1]
            p = subprocess.Popen([{exe!r}, *args], stderr=subprocess.DEVNULL)
            while not glob.glob(os.path.join(out, "*", "metrics.json")) and p.poll() is None:
                time.sleep(0.002)
            p.kill()
            p.wait()
            done = glob.glob(os.path.join(out, "*", "metrics.json"))
            open({str(marker)!r}, "w").write("\\n".join(done))
            sys.exit(137)
        os.execv({exe!r}, [{exe!r}, *args])
        """))
    wrapper.chmod(wrapper.stat().st_mode | stat.S_IEXEC)
    merged = ray_driver.run(SIM_ARGS, 3, tmp_path / "out", b2dr=str(wrapper), retries=2, progress=print)
    assert marker.is_file(), "the first attempt of shard 1 did not run"
    done_before = [p for p in marker.read_text().splitlines() if p]
    assert done_before, "the killed attempt finished no scenario"
    check_equal(single, merged)
    # the scenario finished before the kill was read back, not rerun: its entry (wall time included) is the one
    # the killed attempt wrote
    first = load(done_before[0])
    assert any(sc == first for sc in merged["scenarios"])


def test_reserved_flags_are_refused():
    with pytest.raises(ValueError, match="--shard"):
        ray_driver.run(["sim", "--shard", "0/2"], 2, "/nonexistent", b2dr="b2dr")
