"""DeeP-LCC dataset: generation, atomic write, schema validation, independent re-solve of stored samples."""

import json
import os

import numpy as np
import pytest

from mixed_traffic.apps.dataset import run as run_app
from mixed_traffic.controllers.deeplcc.dataset import (
    DatasetConfig,
    generate_dataset,
    load_dataset,
    nn_inputs,
    validate_dataset,
    write_dataset,
)
from mixed_traffic.controllers.deeplcc.hankel import HankelData
from mixed_traffic.controllers.deeplcc.qp import build_qp, solve_cvxopt


@pytest.fixture(scope="module")
def brake_dataset(tmp_path_factory):
    """Full-size QP (T=2000, t_ini=20, N=50): one hard-brake episode, so constraints bind."""
    cfg = DatasetConfig(episodes=1, episode_seconds=2.5, mix={"brake": 1.0}, brake_start=(1.0, 1.0), workers=1, seed=5)
    path = tmp_path_factory.mktemp("ds") / "brake.npz"
    write_dataset(path, generate_dataset(cfg, progress=False))
    return path


def test_schema_and_shapes(brake_dataset):
    d = load_dataset(brake_dataset)
    N = 50 - 20  # 2.5 s at 0.05 s, minus the t_ini steps filling the window
    assert d["uini"].shape == (N, 40) and d["yini"].shape == (N, 200) and d["eini"].shape == (N, 20)
    assert d["u_opt"].shape == (N, 2) and d["episode"].shape == (N,)
    assert d["Up"].shape == (1, 40, 1931) and d["Yf"].shape == (1, 500, 1931)
    np.testing.assert_array_equal(d["metadata"], [15.0, 20.0, 20, 50, 1.0, 1e3])
    qp = json.loads(str(d["qp"]))
    assert qp["lambda_y"] == 1e3 and qp["dcel_max"] == -5.0 and qp["s_star"] == 20.0
    assert nn_inputs(d).shape == (N, 260)
    assert load_dataset(brake_dataset, hankel=False)["dims"]["columns"] == 1931


def test_stored_samples_resolve_with_cvxopt(brake_dataset):
    """Acceptance: an independent dense interior-point solve (tight tolerances) reproduces u_opt."""
    d = load_dataset(brake_dataset)
    h = HankelData.from_dict({k: d[k][0] for k in ("Up", "Uf", "Ep", "Ef", "Yp", "Yf")}, t_ini=20, n=50)
    qp = build_qp(h, d["qp_params"])
    bound_hit = np.isclose(d["u_opt"], -5.0).any(1)
    picks = [int(np.argmax(bound_hit)), len(d["u_opt"]) - 1]  # one sample at the braking bound, one inside
    assert bound_hit.any() and not bound_hit[picks[1]]
    for i in picks:
        u, status = solve_cvxopt(qp, d["uini"][i], d["yini"][i], d["eini"][i], tol=1e-10, reltol=1e-16)
        assert status == "optimal"
        np.testing.assert_allclose(u[:2], d["u_opt"][i], atol=1e-4)


@pytest.mark.parametrize("key, bad, message", [
    ("uini", np.zeros((3, 40), np.float32), r"'uini' has shape \(3, 40\); expected \(30, 40\)"),
    ("yini", np.zeros((30, 199), np.float32), r"'yini' has shape \(30, 199\)"),
    ("Yf", np.zeros((1, 499, 1931), np.float32), r"'Yf' has shape .* expected \(1, 500, 1931\)"),
    ("metadata", np.zeros(5), r"'metadata' has shape \(5,\); expected \(6,\)"),
    ("qp", np.array(json.dumps({"weight_v": 1.0})), r"'qp' lacks field"),
    ("episode", np.full(30, 3, np.int32), r"'episode' holds values outside"),
])
def test_validation_names_the_key_and_shape(brake_dataset, key, bad, message):
    d = dict(np.load(brake_dataset))
    d[key] = bad
    with pytest.raises(ValueError, match=message):
        validate_dataset(d)
    del d[key]
    with pytest.raises(ValueError, match=f"missing key.*{key}"):
        validate_dataset(d)


def test_bad_config_never_clobbers_existing_output(tmp_path):
    out = tmp_path / "keep.npz"
    out.write_bytes(b"precious")
    base = {"output": str(out), "progress": False, "workers": 1}
    for bad, field in (({"episodes": 0}, "episodes"), ({"hdv_model": "krauss"}, "hdv_model"),
                       ({"mix": {"random9": 1.0}}, "random9"), ({"qp_preset": "fast"}, "qp_preset"),
                       ({"t_ini": 20, "n": 50, "T": 60}, "T")):
        with pytest.raises(ValueError, match=field):
            run_app({**base, **bad})
        assert out.read_bytes() == b"precious"
    with pytest.raises(ValueError, match="overwrite"):
        run_app({**base, "episodes": 1, "overwrite": False})
    with pytest.raises(ValueError, match="output"):
        run_app({**base, "output": str(tmp_path / "x.csv")})
    assert out.read_bytes() == b"precious"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.npz"]  # no temp file left behind


def test_episode_mix_is_in_contiguous_blocks():
    kinds = DatasetConfig(episodes=20).episode_kinds()
    assert kinds.count("random1") == 6 and kinds.count("brake") == 5 and kinds.count("sine5") == 2
    firsts = [kinds.index(k) for k in dict.fromkeys(kinds)]
    assert firsts == sorted(firsts) and kinds == sorted(kinds, key=kinds.index)


def test_write_is_atomic(tmp_path, brake_dataset, monkeypatch):
    out = tmp_path / "d.npz"
    out.write_bytes(b"old")
    d = dict(np.load(brake_dataset))

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError):
        write_dataset(out, d)
    assert out.read_bytes() == b"old" and os.listdir(tmp_path) == ["d.npz"]


def test_idm_switch_changes_the_human_model(tmp_path):
    """Model mismatch study: ``hdv_model=idm`` pre-collects and drives with IDM humans."""
    small = {"episodes": 1, "episode_seconds": 1.5, "T": 300, "t_ini": 5, "n": 10, "workers": 1,
             "mix": {"random1": 1.0}, "progress": False}
    paths = {}
    for model in ("ovm", "idm"):
        paths[model] = tmp_path / f"{model}.npz"
        run_app({**small, "hdv_model": model, "output": str(paths[model])})
    ovm, idm = load_dataset(paths["ovm"]), load_dataset(paths["idm"])
    assert json.loads(str(idm["config"]))["hdv_model"] == "idm"
    np.testing.assert_array_equal(ovm["Up"], idm["Up"])  # same excitation (same seed) ...
    assert np.abs(ovm["Yp"] - idm["Yp"]).max() > 0.1  # ... different human response
    # IDM equilibrium gap at 15 m/s is 20.66 m: CAV spacing errors start near +0.66 m, not -5 m
    assert abs(float(idm["yini"][0, 8]) - 0.66) < 0.1 and abs(float(ovm["yini"][0, 8]) + 5.0) < 0.1
