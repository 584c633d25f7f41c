"""Any registered policy runs the whole recipe through `capvector run`: the flow backbone and a plugin.

The plugin (`tests/policy_plugin`) is a policy defined outside capvector_core, found through the
`capvector.policies` entry point of its dist-info on PYTHONPATH, exactly as an installed package's is.
"""

import json

import pytest
from conftest import REPO, run_cli

from capvector.artifacts.api import ArtifactsAPI
from capvector.core.policies.base import CONFIG_METADATA_KEY, read_metadata

PLUGIN_PATH = str(REPO / "tests" / "policy_plugin")


@pytest.mark.slow
@pytest.mark.parametrize(
    "policy_type,env",
    [("flow", {}), ("mlp", {"PYTHONPATH": PLUGIN_PATH})],
    ids=["flow", "plugin"],
)
def test_smoke_run_trains_merges_regularizes_and_scores_the_policy_type(tmp_path, policy_type, env):
    home = tmp_path / "home"
    proc = run_cli(
        "run", "--preset", "smoke", "--set", f"policy.type={policy_type}", "--json", home=home, env=env
    )
    ids = json.loads(proc.stdout)
    api = ArtifactsAPI(str(home))
    for key in ("pretrained", "standard", "auxiliary", "meta", *ids["checkpoints"].values()):
        checkpoint = ids.get(key, key)
        config = json.loads(read_metadata(api.path(checkpoint))[CONFIG_METADATA_KEY])
        assert config["type"] == policy_type, key  # (this process has no plugin to rebuild it with)

    capvector = api.get(ids["checkpoints"]["capvector/seed0"])
    roles = {p.role: p.id for p in capvector.parents}
    assert roles["init"] == ids["meta"] and roles["regularized_by"] == ids["vector"]
    curve = capvector.config["curve"]
    assert all(row["orthogonal"] > 0 for row in curve[1:])  # the regularizer acted once θ left θ_meta
    aux_curve = api.get(ids["auxiliary"]).config["curve"]
    assert "dynamics" in aux_curve[0]  # the auxiliary objective read the policy's features

    scores = api.query(
        "SELECT evaluation_id, task, n_episodes FROM eval_tasks WHERE evaluation_id IN (?, ?, ?)",
        list(ids["evaluations"].values()),
    )
    assert len(scores) == 3 and set(scores["n_episodes"]) == {2}
