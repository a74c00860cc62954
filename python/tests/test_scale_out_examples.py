"""examples/slurm_array.sh and examples/k8s_indexed_job.yaml, checked without a cluster: the Slurm script's
syntax (bash -n), its dry run (the b2dr command of each SLURM_ARRAY_TASK_ID), its refusals, and a real run of
its three array tasks (sim, tiny) that merges to the single run; the manifest parsed as YAML, its Indexed Job
fields, and every field checked against the Kubernetes API's models (the `kubernetes` client package) when
that is installed. Neither sbatch nor a Kubernetes API server runs here: docs/scale_out.md says what that leaves
unchecked."""
import os
import shlex
import subprocess
import sys

import pytest

from scale_helpers import REPO, SIM_ARGS, b2dr_binary, deterministic, load

SLURM = REPO / "examples" / "slurm_array.sh"
K8S = REPO / "examples" / "k8s_indexed_job.yaml"


def slurm(env, *args):
    e = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
    e.update(env)
    return subprocess.run(["bash", str(SLURM), *args], env=e, capture_output=True, text=True)


def test_slurm_script_syntax_and_dry_run():
    subprocess.run(["bash", "-n", str(SLURM)], check=True)
    text = SLURM.read_text()
    assert "#SBATCH --requeue" in text and "#SBATCH --array=0-2" in text
    for k in range(3):
        p = slurm({"SLURM_ARRAY_TASK_ID": str(k), "SLURM_ARRAY_TASK_COUNT": "3", "B2DR_DRY_RUN": "1",
                   "B2DR_OUT": "/shared/out"}, "run", "--scenario", "a,b", "--renderer", "b2dr")
        assert p.returncode == 0, p.stderr
        assert shlex.split(p.stdout) == ["b2dr", "run", "--scenario", "a,b", "--renderer", "b2dr", "--shard",
                                         f"{k}/3", "--resume", "--out", f"/shared/out/shard-{k}"]
    # an array starting at 1 (--array=1-3) still deals shards 0..2
    p = slurm({"SLURM_ARRAY_TASK_ID": "3", "SLURM_ARRAY_TASK_MIN": "1", "SLURM_ARRAY_TASK_COUNT": "3",
               "B2DR_DRY_RUN": "1"}, "sim")
    assert "--shard 2/3" in p.stdout, p.stderr


@pytest.mark.parametrize("env,args,word", [
    ({}, ["sim"], "SLURM_ARRAY_TASK_ID"),
    ({"SLURM_ARRAY_TASK_ID": "0", "SLURM_ARRAY_TASK_COUNT": "3"}, [], "give the b2dr command"),
    ({"SLURM_ARRAY_TASK_ID": "3", "SLURM_ARRAY_TASK_COUNT": "3"}, ["sim"], "outside"),
    ({"SLURM_ARRAY_TASK_ID": "0", "SLURM_ARRAY_TASK_COUNT": "3"}, ["sim", "--out", "x"], "set by this script"),
])
def test_slurm_script_refusals(env, args, word):
    p = slurm(dict(env, B2DR_DRY_RUN="1"), *args)
    assert p.returncode != 0 and word in p.stderr, p.stderr


def test_slurm_array_tasks_run_and_merge_to_the_single_run(tmp_path):
    exe = b2dr_binary()
    subprocess.run([exe, *SIM_ARGS, "--out", str(tmp_path / "single")], check=True, capture_output=True)
    env = {"B2DR_BIN": exe, "B2DR_OUT": str(tmp_path / "scale"), "SLURM_ARRAY_TASK_COUNT": "3"}
    for k in range(3):
        p = slurm(dict(env, SLURM_ARRAY_TASK_ID=str(k)), *SIM_ARGS)
        assert p.returncode == 0, p.stderr
    # a requeued task resumes (nothing left to do) and leaves the same results
    p = slurm(dict(env, SLURM_ARRAY_TASK_ID="1", SLURM_RESTART_COUNT="1"), *SIM_ARGS)
    assert p.returncode == 0 and "restart 1" in p.stderr, p.stderr
    dirs = [str(tmp_path / "scale" / f"shard-{k}") for k in range(3)]
    subprocess.run([exe, "merge", *dirs, "--out", str(tmp_path / "merged")], check=True, capture_output=True)
    single, merged = load(tmp_path / "single" / "metrics.json"), load(tmp_path / "merged" / "metrics.json")
    assert merged["cls"] == single["cls"]
    assert deterministic(merged) == deterministic(single)


def job():
    yaml = pytest.importorskip("yaml", reason="PyYAML is not installed")
    docs = [d for d in yaml.safe_load_all(K8S.read_text()) if d]
    assert len(docs) == 1
    return docs[0]


def test_k8s_manifest_is_an_indexed_job_of_shards():
    j = job()
    assert (j["apiVersion"], j["kind"]) == ("batch/v1", "Job")
    spec = j["spec"]
    assert spec["completionMode"] == "Indexed"
    n = spec["completions"]
    assert spec["parallelism"] == n and spec["backoffLimit"] >= 1
    pod = spec["template"]["spec"]
    assert pod["restartPolicy"] in ("Never", "OnFailure")
    (c,) = pod["containers"]
    env = {e["name"]: e["value"] for e in c["env"]}
    assert env["B2DR_SHARDS"] == str(n)
    assert "graphics" in env["NVIDIA_DRIVER_CAPABILITIES"]
    cmd = " ".join(c["command"] + c["args"])
    assert '--shard "${JOB_COMPLETION_INDEX}/${B2DR_SHARDS}"' in cmd
    assert "--resume" in cmd and '--out "/out/shard-${JOB_COMPLETION_INDEX}"' in cmd
    assert c["resources"]["limits"]["nvidia.com/gpu"] == 1
    mounts = {m["name"]: m["mountPath"] for m in c["volumeMounts"]}
    assert mounts["out"] == "/out"
    assert {v["name"] for v in pod["volumes"]} >= set(mounts)
    # the shell line the pod runs, for index 2: the b2dr command of shard 2/3
    line = c["args"][0].replace("exec b2dr", "printf '%s\\n' b2dr")
    p = subprocess.run(["sh", "-c", line], env={"JOB_COMPLETION_INDEX": "2", "B2DR_SHARDS": env["B2DR_SHARDS"]},
                       capture_output=True, text=True, check=True)
    words = p.stdout.split()
    assert words[words.index("--shard") + 1] == "2/3" and words[words.index("--out") + 1] == "/out/shard-2"


def check_model(value, model_name, path, api):
    """Every field of `value` is a field of the Kubernetes model `model_name`, recursively, with its type."""
    import kubernetes.client.models as models

    if model_name in ("object", "str", "int", "bool", "float", "datetime"):
        want = {"str": str, "int": int, "bool": bool, "float": (int, float)}.get(model_name)
        if want:
            assert isinstance(value, want), f"{path}: {value!r} is not {model_name}"
        return
    # both spellings of the client's type names: list[X] / dict(str, X) and List[X] / Dict[str, X]
    if model_name.startswith("List["):
        model_name = "list[" + model_name[5:]
    if model_name.startswith("Dict["):
        model_name = "dict(" + model_name[5:-1] + ")"
    if model_name.startswith("list["):
        assert isinstance(value, list), f"{path}: not a list"
        for i, v in enumerate(value):
            check_model(v, model_name[5:-1], f"{path}[{i}]", api)
        return
    if model_name.startswith("dict("):
        assert isinstance(value, dict), f"{path}: not a map"
        inner = model_name[5:-1].split(", ", 1)[1]
        for k, v in value.items():
            if inner == "str" and isinstance(v, (int, float)):  # resource quantities: 1 == "1"
                continue
            check_model(v, inner, f"{path}.{k}", api)
        return
    cls = getattr(models, model_name)
    assert isinstance(value, dict), f"{path}: not an object ({model_name})"
    by_json = {j: a for a, j in cls.attribute_map.items()}
    for k, v in value.items():
        assert k in by_json, f"{path}.{k}: no field {k!r} in {model_name}"
        check_model(v, cls.openapi_types[by_json[k]], f"{path}.{k}", api)


def test_k8s_manifest_matches_the_api_schema():
    try:
        import kubernetes  # noqa: F401
    except ImportError as e:
        print(f"SKIP schema check: the kubernetes client package is not installed ({e})", file=sys.stderr)
        pytest.skip(f"the kubernetes client package is not installed ({e}); pip install kubernetes")
    check_model(job(), "V1Job", "job", None)
