"""OnnxPolicy, resolve_policy and make_test_policy: loading, running, and one-line PolicyErrors."""

from __future__ import annotations

import numpy as np
import onnx
import pytest

from cfrace.contract import encode_meta
from cfrace.drone import load_profile
from cfrace.contract.observations import LAYOUTS
from cfrace.errors import PolicyError
from cfrace.policygraph import build_model
from cfrace.policy import OnnxPolicy, resolve_policy

from policyfiles import make_test_policy


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and text
    return text


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_kinds_and_metadata(tmp_path, layout):
    obstacles = LAYOUTS[layout].world_position
    d = LAYOUTS[layout].dim
    obs = np.random.default_rng(1).normal(size=(7, d)).astype(np.float32)
    hover = OnnxPolicy(make_test_policy(tmp_path / "h.onnx", layout, "complex", obstacles, "hover"))
    assert hover.meta["obs_dim"] == d and hover.meta["obs_layout"] == layout
    assert hover.meta["obstacles"] is obstacles and hover.meta["policy_hz"] == 50.0
    act = hover(obs)
    assert act.shape == (7, 4) and act.dtype == np.float32
    t = load_profile("cf2x_paper").max_thrust_weights
    np.testing.assert_allclose((act[:, 0] + 1) / 2 * t, 1.0, rtol=1e-6)  # one weight of thrust
    assert np.all(act[:, 1:] == 0)
    assert np.all(OnnxPolicy(make_test_policy(tmp_path / "z.onnx", layout, "complex", obstacles, "zeros"))(obs) == 0)
    assert np.isnan(OnnxPolicy(make_test_policy(tmp_path / "n.onnx", layout, "complex", obstacles, "nan"))(obs)).all()
    rnd = OnnxPolicy(make_test_policy(tmp_path / "r.onnx", layout, "complex", obstacles, "random"))
    a = rnd(obs)
    assert np.all(np.abs(a) <= 1) and a.std() > 0.05
    np.testing.assert_array_equal(a, rnd(obs))          # deterministic
    np.testing.assert_array_equal(rnd(obs[0]), a[0])    # single observation


def test_check_track_and_obstacles(tmp_path):
    pol = OnnxPolicy(make_test_policy(tmp_path / "p.onnx", "race45_obstacles", "lemniscate", True))
    pol.check("lemniscate", True)
    with pytest.raises(PolicyError) as e:
        pol.check("complex", True)
    assert "lemniscate" in _one_line(e)
    with pytest.raises(PolicyError) as e:
        pol.check("lemniscate", False)
    assert "obstacles" in _one_line(e)


def test_wrong_observation_shape(tmp_path):
    pol = OnnxPolicy(make_test_policy(tmp_path / "p.onnx", "race42", "complex", False))
    with pytest.raises(PolicyError):
        pol(np.zeros((2, 45), np.float32))


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(PolicyError) as e:
        OnnxPolicy(tmp_path / "nope.onnx")
    assert "no such" in _one_line(e)
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"this is not a protobuf at all \x00\xff" * 10)
    with pytest.raises(PolicyError) as e:
        OnnxPolicy(bad)
    assert "not a valid ONNX" in _one_line(e)
    good = make_test_policy(tmp_path / "good.onnx", "race42", "complex", False, "random")
    data = good.read_bytes()
    (tmp_path / "trunc.onnx").write_bytes(data[: len(data) // 2])
    with pytest.raises(PolicyError):
        OnnxPolicy(tmp_path / "trunc.onnx")
    with pytest.raises(PolicyError):
        OnnxPolicy(tmp_path)  # a directory


def _meta(**over):
    p = load_profile("cf2x_paper")
    meta = {"method": "ours", "track": "complex", "obstacles": False, "obs_layout": "race42", "obs_dim": 42,
            "max_thrust_weights": p.max_thrust_weights, "max_rates_deg": list(p.max_rates_deg),
            "policy_hz": 50.0, "drone_profile": p.name, "train_steps": 0, "seed": 0, "cfrace_version": "0"}
    meta.update(over)
    return meta


def _write(path, meta, in_dim=42, out_dim=4, rename=None):
    model = build_model([("linear", np.zeros((out_dim, in_dim), np.float32), np.zeros(out_dim, np.float32))],
                        None, None, _meta(), in_dim) if out_dim == 4 else None
    if model is None:  # build a wrong-output model by editing a valid one
        model = build_model([("linear", np.zeros((4, in_dim), np.float32), np.zeros(4, np.float32))],
                            None, None, _meta(), in_dim)
        model.graph.output[0].type.tensor_type.shape.dim[1].dim_value = out_dim
    if rename:
        model.graph.input[0].name = rename
        model.graph.node[0].input[0] = rename
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, encode_meta(meta))
    onnx.save_model(model, str(path))
    return path


def test_metadata_errors(tmp_path):
    OnnxPolicy(_write(tmp_path / "ok.onnx", _meta()))  # the baseline loads
    meta = _meta()
    del meta["track"]
    with pytest.raises(PolicyError) as e:
        OnnxPolicy(_write(tmp_path / "a.onnx", meta))
    assert "track" in _one_line(e)
    with pytest.raises(PolicyError) as e:  # obs_dim inconsistent with the layout
        OnnxPolicy(_write(tmp_path / "b.onnx", _meta(obs_dim=45), in_dim=45))
    assert "obs_layout" in _one_line(e)
    with pytest.raises(PolicyError):  # graph input disagrees with metadata
        OnnxPolicy(_write(tmp_path / "c.onnx", _meta(), in_dim=45))
    with pytest.raises(PolicyError):
        OnnxPolicy(_write(tmp_path / "d.onnx", _meta(obs_layout="nope")))
    with pytest.raises(PolicyError):
        OnnxPolicy(_write(tmp_path / "e.onnx", _meta(obstacles=True)))
    with pytest.raises(PolicyError):
        OnnxPolicy(_write(tmp_path / "f.onnx", _meta(method="ds")))
    with pytest.raises(PolicyError):
        OnnxPolicy(_write(tmp_path / "g.onnx", _meta(max_rates_deg=[1, 2])))


def test_wrong_names_and_sizes(tmp_path):
    with pytest.raises(PolicyError) as e:
        OnnxPolicy(_write(tmp_path / "n.onnx", _meta(), rename="x"))
    assert "'obs'" in _one_line(e)
    with pytest.raises(PolicyError):
        OnnxPolicy(_write(tmp_path / "o.onnx", _meta(), out_dim=3))


def test_resolve_policy(tmp_path, monkeypatch):
    import cfrace.policy as mod

    monkeypatch.setattr(mod, "POLICIES_DIR", tmp_path)
    make_test_policy(tmp_path / "ours_complex_obstacles.onnx", "race45_obstacles", "complex", True)
    assert resolve_policy("ours", "complex", True) == tmp_path / "ours_complex_obstacles.onnx"
    with pytest.raises(PolicyError) as e:
        resolve_policy("ds", "complex", False)
    assert "ds_complex.onnx" in _one_line(e)
    p = make_test_policy(tmp_path / "x" / "any.onnx", "solo36", "complex", False)
    assert resolve_policy(str(p), "complex", False) == p
    with pytest.raises(PolicyError):
        resolve_policy(tmp_path / "missing.onnx", "complex", False)


def test_schema_versions(tmp_path):
    """Files from before schema_version (the shipped ones) load as schema 1; new files carry the
    current version; a newer schema or a bad version is one line naming the file."""
    from cfrace.contract import SCHEMA_VERSION
    from cfrace.paths import POLICIES_DIR

    shipped = OnnxPolicy(POLICIES_DIR / "ds_lemniscate.onnx")
    assert "schema_version" not in shipped.meta   # written before the key existed: schema 1
    v1 = OnnxPolicy(_write(tmp_path / "v1.onnx", _meta()))
    assert "schema_version" not in v1.meta
    new = OnnxPolicy(make_test_policy(tmp_path / "new.onnx", "race42", "complex", False))
    assert new.meta["schema_version"] == SCHEMA_VERSION
    with pytest.raises(PolicyError) as e:
        OnnxPolicy(_write(tmp_path / "future.onnx", _meta(schema_version=SCHEMA_VERSION + 1)))
    assert "future.onnx" in _one_line(e) and f"schema {SCHEMA_VERSION + 1}" in _one_line(e)
    with pytest.raises(PolicyError) as e:
        OnnxPolicy(_write(tmp_path / "odd.onnx", _meta(schema_version="two")))
    assert "schema_version" in _one_line(e)
