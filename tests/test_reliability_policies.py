"""Untrusted policy files and user controllers in ``wl evaluate``: no code runs from a policy file, a missing
or broken file is one error line naming it, and a misbehaving controller is one error line naming the
controller, the episode and the step."""

from __future__ import annotations

import argparse
import base64
import hashlib
import json
import pickle
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

import wl.cli
from agents.policy_files import PolicyFileError
from agents.ppo import PPOConfig, build_model, load_policy, make_env, save_model_files

POLICIES = Path(__file__).resolve().parents[1] / "agents" / "policies"


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = wl.cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    """The error line that ends stderr (after any progress lines), with no traceback."""
    lines = err.strip().splitlines()
    assert "Traceback" not in err and [line for line in lines if line.startswith("wl: error:")] == lines[-1:], err
    return lines[-1]


class _WritesMarker:
    """Unpickling this object runs code: it writes the marker file."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').write('code ran')",)


def _evil_pickle(marker: Path) -> bytes:
    return pickle.dumps(_WritesMarker(marker))


def _evil_sb3_zip(path: Path, marker: Path) -> None:
    """A zip laid out as stable-baselines3 saves one, whose ``data`` entry holds a serialized object (SB3
    unpickles those with cloudpickle)."""
    data = {"policy_class": {":type:": "<class 'abc.ABCMeta'>",
                             ":serialized:": base64.b64encode(_evil_pickle(marker)).decode()}}
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("data", json.dumps(data))
        z.writestr("_stable_baselines3_version", "2.3.0")


@pytest.fixture
def marker(tmp_path: Path) -> Path:
    m = tmp_path / "MARKER"
    pickle.loads(_evil_pickle(m))  # the payload is live: unpickling it does write the marker
    assert m.read_text() == "code ran"
    m.unlink()
    return m


def _copy_shipped(dst: Path, braking: str = "tc", parts=(".safetensors", "_vecnormalize.npz", ".json")) -> Path:
    for part in parts:
        shutil.copy(POLICIES / f"ppo_{braking}{part}", dst / f"ppo_{braking}{part}")
    return dst / f"ppo_{braking}"


def _reseal(stem: Path, key: str, file: Path) -> None:
    """Record ``file``'s new sha256 in the metadata, so that a check deeper than the checksum is reached."""
    meta_path = stem.with_name(stem.name + ".json")
    meta = json.loads(meta_path.read_text())
    meta["files"][key]["sha256"] = hashlib.sha256(file.read_bytes()).hexdigest()
    meta_path.write_text(json.dumps(meta))


@pytest.fixture
def own_run(tmp_path: Path) -> tuple[Path, object, object]:
    """A folder as training writes it (model.zip, vecnormalize.pkl, progress.json, policy.*) of an untrained
    tiny model, with the model and its VecNormalize env."""
    cfg = PPOConfig(num_envs=2, n_steps=8, batch_size=16, net_arch=(8,), score=False, progress_bar=False,
                    log_dir=str(tmp_path), run_name="own")
    env = make_env(cfg)
    env.reset()
    model = build_model(cfg, env, tmp_path / "tb")
    folder = save_model_files(model, env, tmp_path / "own", {"braking": "service", "num_timesteps": 0}, export=True)
    return folder, model, env


# ------------------------------------------------------------------------------------------ no pickle
@pytest.mark.parametrize("layout", ["zip+pkl", "pkl", "run folder"])
def test_pickle_files_never_run_code_without_trust(tmp_path, capsys, marker, layout):
    if layout == "run folder":
        folder = tmp_path / "run" / "final"
        folder.mkdir(parents=True)
        _evil_sb3_zip(folder / "model.zip", marker)
        (folder / "vecnormalize.pkl").write_bytes(_evil_pickle(marker))
        (folder / "summary.json").write_text(json.dumps({"braking": "service"}))
        model = tmp_path / "run"
    else:
        _evil_sb3_zip(tmp_path / "evil.zip", marker)
        (tmp_path / "evil_vecnormalize.pkl").write_bytes(_evil_pickle(marker))
        (tmp_path / "evil.json").write_text(json.dumps({"braking": "service"}))
        model = tmp_path / ("evil.zip" if layout == "zip+pkl" else "evil_vecnormalize.pkl")
    out = tmp_path / "e.json"
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", model, "--episodes", 1, "--no-score",
                        "--out", out)
    line = _one_error_line(err)
    assert code == 2 and "--trust-pickle" in line and "pickle-free" in line and ".zip" in line
    assert not marker.exists() and not out.exists()
    with pytest.raises(PolicyFileError, match="trust_pickle=True"):
        load_policy(model)
    assert not marker.exists()


def test_pickle_in_a_normalization_npz_is_refused(tmp_path, capsys, marker):
    stem = _copy_shipped(tmp_path)
    npz = tmp_path / "ppo_tc_vecnormalize.npz"
    evil = np.empty(1, dtype=object)
    evil[0] = _WritesMarker(marker)
    with open(npz, "wb") as f:  # an object array: np.save pickles it
        np.savez(f, mean=evil, var=np.ones(12), clip_obs=10.0, epsilon=1e-8, norm_obs=True)
    _reseal(stem, "normalization", npz)
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", stem, "--episodes", 1, "--no-score",
                        "--out", tmp_path / "e.json")
    assert code == 2 and str(npz) in _one_error_line(err) and "allow_pickle" in err
    assert not marker.exists()


@pytest.mark.parametrize("entries, needle", [
    ({"mean": np.zeros(12), "var": np.ones(12), "clip_obs": np.ones(3), "epsilon": 1e-8, "norm_obs": True}, "single"),
    ({"mean": np.zeros(12), "var": np.ones(12), "clip_obs": 10.0, "epsilon": 1e-8, "norm_obs": "yes"}, "bool"),
    ({"mean": np.zeros(11), "var": np.ones(12), "clip_obs": 10.0, "epsilon": 1e-8, "norm_obs": True}, "12 floats"),
    ({"mean": np.full(12, np.nan), "var": np.ones(12), "clip_obs": 10.0, "epsilon": 1e-8, "norm_obs": True}, "finite"),
    ({"mean": np.zeros(12), "var": np.ones(12), "clip_obs": 10.0, "norm_obs": True}, "no entry 'epsilon'"),
    # (each passed once: NaN at the first step, or a policy that failed every episode quietly)
    ({"mean": np.zeros(12), "var": np.zeros(12), "clip_obs": np.inf, "epsilon": 1e-300, "norm_obs": True}, "finite number > 0"),
    ({"mean": np.zeros(12), "var": np.ones(12), "clip_obs": 10.0, "epsilon": 1e308, "norm_obs": True}, "epsilon in"),
])
def test_normalization_entries_are_checked(tmp_path, entries, needle):
    stem = _copy_shipped(tmp_path)
    npz = tmp_path / "ppo_tc_vecnormalize.npz"
    np.savez(npz, **entries)
    _reseal(stem, "normalization", npz)
    with pytest.raises(PolicyFileError, match=needle):
        load_policy(stem)


@pytest.mark.parametrize("tamper, needle", [
    ({"class": "os.system"}, "network.class"),
    ({"activation_fn": "Evil"}, "network.activation_fn"),
    ({"net_arch": {"pi": [10**9]}}, "network.net_arch"),
    ({"log_std_init": 10**400}, "network.log_std_init"),  # was a bare OverflowError
    ({"observation_space": {"shape": [13], "low": [0.0] * 13, "high": [1.0] * 13}}, "has at least"),
    ({"squash_output": True}, "network.squash_output"),  # was stable-baselines3's bare AssertionError
    # (a float32 overflow: the bound turned inf with a RuntimeWarning)
    ({"observation_space": {"shape": [12], "low": [-1e308] * 12, "high": [1.0] * 12}}, "float32"),
    # (predict clipped every action to these: [0.05, 0.1] instead of the envs' [-1, 1], without a word)
    ({"action_space": {"shape": [4], "low": [0.05] * 4, "high": [0.1] * 4}}, "Box\\(-1, 1\\)"),
])
def test_metadata_names_only_known_classes_and_sane_shapes(tmp_path, tamper, needle):
    stem = _copy_shipped(tmp_path)
    meta_path = tmp_path / "ppo_tc.json"
    meta = json.loads(meta_path.read_text())
    meta["network"].update(tamper)
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(PolicyFileError, match=needle):
        load_policy(stem)


def test_a_huge_integer_log_std_init_loads_as_the_float_it_is(tmp_path):
    """``"log_std_init": 10**30`` (a finite number, so accepted) overflowed torch's int64 (a bare OverflowError);
    it only seeds a parameter the weights then set."""
    stem = _copy_shipped(tmp_path)
    meta_path = tmp_path / "ppo_tc.json"
    meta = json.loads(meta_path.read_text())
    meta["network"]["log_std_init"] = 10**30
    meta_path.write_text(json.dumps(meta))
    shipped, tampered = load_policy(POLICIES / "ppo_tc"), load_policy(stem)
    obs = np.zeros(12, np.float32)
    assert np.array_equal(shipped.act(obs), tampered.act(obs))


@pytest.mark.parametrize("config, needle", [("abc", "config must be an object"), ([1], "config must be an object"),
                                            ({"env_id": ["x"]}, "config.env_id"), ({"env_id": "Foo-v0"}, "none of")])
def test_the_metadata_config_is_checked(tmp_path, config, needle):
    """The metadata has no checksum of its own: its training config is checked like the rest (was a bare
    AttributeError or TypeError)."""
    stem = _copy_shipped(tmp_path)
    meta_path = tmp_path / "ppo_tc.json"
    meta_path.write_text(json.dumps({**json.loads(meta_path.read_text()), "config": config}))
    with pytest.raises(PolicyFileError, match=needle):
        load_policy(stem)


def test_a_normalization_header_that_claims_a_huge_array_is_refused_before_reading_it(tmp_path):
    """A .npy header claiming 2^45 floats made numpy allocate 256 TiB (MemoryError); the shapes are read from
    the headers first."""
    import io
    import zipfile

    stem = _copy_shipped(tmp_path)
    npz = tmp_path / "ppo_tc_vecnormalize.npz"
    with zipfile.ZipFile(npz) as z:
        entries = {i.filename: z.read(i) for i in z.infolist()}
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (2**45,)})
    entries["mean.npy"] = buf.getvalue() + b"\0" * 64
    with zipfile.ZipFile(npz, "w") as z:
        for name, data in entries.items():
            z.writestr(name, data)
    _reseal(stem, "normalization", npz)
    with pytest.raises(PolicyFileError, match="mean.npy"):
        load_policy(stem)


def test_weights_must_be_finite_and_braking_known(tmp_path):
    from safetensors.torch import load, save

    stem = _copy_shipped(tmp_path)
    weights = tmp_path / "ppo_tc.safetensors"
    state = load(weights.read_bytes())
    state["action_net.bias"][0] = float("nan")
    weights.write_bytes(save(state))
    _reseal(stem, "weights", weights)
    with pytest.raises(PolicyFileError, match="every weight must be a finite float"):
        load_policy(stem)
    (tmp_path / "b").mkdir()
    stem = _copy_shipped(tmp_path / "b")
    meta_path = stem.with_name("ppo_tc.json")
    meta_path.write_text(json.dumps({**json.loads(meta_path.read_text()), "braking": "foo"}))
    with pytest.raises(PolicyFileError, match='braking must be "service" or "tc"'):
        load_policy(stem)


@pytest.mark.parametrize("tamper, needle", [
    ("float8 weights", "every weight must be a finite float32|dtype"),  # (isfinite failed; F8_E5M2 drove another cycle)
    ("million tensors", "tensors; a policy network has at most"),  # (22 s and 1.7 GB, then "Unexpected key(s)")
    ("huge metadata", "a policy's is at most"),  # (400 MB of whitespace: 1 GB read, and accepted)
    ("5000-digit integer", "policy metadata .* is unreadable"),  # (Python's int-digits error, naming no file)
    ("low > high", "its network cannot be built"),  # (gymnasium's Box error, naming no file)
    ("extra npz entries", "is none of"),  # (300 000 of them: 14 s, accepted)
    ("2 GB per item", "normalization file .* is unreadable: MemoryError"),  # (numpy's "Unable to allocate 7.28 TiB",
    # a traceback); stop 59's:
    ("long double statistics", "must be float16/32/64"),  # (1e400 passed the finiteness check, then became inf)
    ("header nested deep", "weights file .* is unreadable: RecursionError"),  # (a RecursionError traceback)
    ("dtype a list", r"tensors of dtype .*F32.*; the weights are float32"),  # (TypeError: unhashable type: 'list')
    ("sparse 1.2 GB weights", "weights file .* is 1288490188 bytes; a policy's is at most"),  # (read whole to be hashed:
    # 5 s and 1.4 GB)
    ("sparse 1 MB normalization", "normalization file .* bytes; a policy's is at most")])
def test_hostile_policy_files_are_one_error_naming_the_file(tmp_path, tamper, needle):
    import torch
    from safetensors.torch import load, save

    stem = _copy_shipped(tmp_path)
    weights, meta_path, npz = (tmp_path / f"ppo_tc{part}" for part in (".safetensors", ".json", "_vecnormalize.npz"))
    meta = json.loads(meta_path.read_text())
    if tamper == "float8 weights":
        weights.write_bytes(save({k: v.to(torch.float8_e5m2) for k, v in load(weights.read_bytes()).items()}))
        _reseal(stem, "weights", weights)
    elif tamper == "million tensors":
        weights.write_bytes(save({**load(weights.read_bytes()), **{f"x{i}": torch.zeros(0) for i in range(1000)}}))
        _reseal(stem, "weights", weights)
    elif tamper == "huge metadata":
        meta_path.write_text(json.dumps(meta) + " " * (2**20 + 1))
    elif tamper == "5000-digit integer":
        meta_path.write_text(json.dumps(meta).replace('"log_std_init": ', '"log_std_init": ' + "9" * 5000 + ", \"x\": ", 1))
    elif tamper == "low > high":
        space = meta["network"]["observation_space"]
        space["low"], space["high"] = space["high"], space["low"]
        meta_path.write_text(json.dumps(meta))
    elif tamper in ("header nested deep", "dtype a list"):
        body = weights.read_bytes()
        n = int.from_bytes(body[:8], "little")
        header = json.loads(body[8:8 + n])
        if tamper == "header nested deep":
            text = b"[" * 100_000 + b"]" * 100_000
        else:
            next(v for k, v in header.items() if k != "__metadata__")["dtype"] = ["F32"]
            text = json.dumps(header).encode()
        weights.write_bytes(len(text).to_bytes(8, "little") + text + body[8 + n:])
        _reseal(stem, "weights", weights)
    elif tamper.startswith("sparse"):
        with open(weights if "weights" in tamper else npz, "r+b") as f:  # (sparse: no disk used)
            f.truncate(1288490188 if "weights" in tamper else 2**20)
    else:
        with np.load(npz) as f:
            data = {k: f[k] for k in f.files}
        if tamper == "extra npz entries":
            data.update({f"junk{i}": np.zeros(1) for i in range(50)})
        if tamper == "2 GB per item":
            del data["mean"]
        if tamper == "long double statistics":
            data["var"] = np.full(data["var"].shape, np.longdouble("1e400"))
        np.savez(npz, **data)
        if tamper == "2 GB per item":  # (a header under the value cap that asks numpy for 4000 x 2 GB; no data behind it)
            import io
            import zipfile

            header = io.BytesIO()
            np.lib.format.write_array_header_1_0(header, {"descr": "|S2000000000", "fortran_order": False, "shape": (4000,)})
            with zipfile.ZipFile(npz, "a") as z:
                z.writestr("mean.npy", header.getvalue())
        _reseal(stem, "normalization", npz)
    with pytest.raises(PolicyFileError, match=needle):
        load_policy(stem)


def test_a_policy_whose_env_takes_another_action_is_refused_at_loading(tmp_path):
    """A plan policy (14 numbers) told its env is WheelLoaderTarget-v6 (4) loaded and failed at the first step, naming
    the controller, not the policy."""
    for part in (".safetensors", "_vecnormalize.npz", ".json"):
        shutil.copy(POLICIES / f"plan_target_tc{part}", tmp_path / f"plan_target_tc{part}")
    meta_path = tmp_path / "plan_target_tc.json"
    meta = json.loads(meta_path.read_text())
    meta["config"]["env_id"] = "WheelLoaderTarget-v6"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(PolicyFileError, match="gives 14 numbers per action; its env 'WheelLoaderTarget-v6' takes 4"):
        load_policy(tmp_path / "plan_target_tc")


def test_metadata_larger_than_its_weights_is_refused_before_building(tmp_path, monkeypatch):
    """A small file declaring the largest allowed network (16 layers of 4096 each side: ~2 GB to build) is refused
    by counting its weights, before any layer is built."""
    import agents.policy_files as pf

    stem = _copy_shipped(tmp_path)
    meta_path = tmp_path / "ppo_tc.json"
    meta = json.loads(meta_path.read_text())
    meta["network"]["net_arch"] = {"pi": [4096] * 16, "vf": [4096] * 16}
    meta_path.write_text(json.dumps(meta))

    def never(net):
        raise AssertionError("the network was built")

    monkeypatch.setattr(pf, "build_network", never)
    with pytest.raises(PolicyFileError, match="holds 10313 numbers; the network of ppo_tc.json has at least 5"):
        load_policy(stem)


def test_trusted_zip_of_an_own_run_loads_with_the_flag(own_run, capsys, tmp_path):
    folder, model, env = own_run
    obs = np.random.default_rng(0).uniform(0.0, 1.0, (16, 12)).astype(np.float32)
    expected = model.predict(env.normalize_obs(obs), deterministic=True)[0]
    np.testing.assert_array_equal(load_policy(folder / "model.zip", trust_pickle=True).act(obs), expected)
    np.testing.assert_array_equal(load_policy(folder).act(obs), expected)  # its pickle-free twin, no flag
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", folder / "model.zip", "--trust-pickle",
                        "--episodes", 1, "--no-score", "--out", tmp_path / "e.json")
    assert code == 0, err
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--trust-pickle", "--out", tmp_path / "o.json")
    assert code == 2 and "--trust-pickle is for --controller ppo" in _one_error_line(err)


def test_help_says_trust_pickle_is_for_trusted_input(capsys):
    code, out, _ = _run(capsys, "evaluate", "--help")
    assert code == 0 and "--trust-pickle" in out and "trusted input only" in " ".join(out.split())


# ------------------------------------------------------------------------------------------ companions
@pytest.mark.parametrize("present, missing", [
    ((".safetensors",), ("_vecnormalize.npz", ".json")),
    ((".safetensors", ".json"), ("_vecnormalize.npz",)),
    ((".safetensors", "_vecnormalize.npz"), (".json",)),
    ((".json",), (".safetensors", "_vecnormalize.npz")),
])
def test_missing_companions_are_named(tmp_path, capsys, present, missing):
    stem = _copy_shipped(tmp_path, parts=present)
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", stem.with_name(stem.name + present[0]),
                        "--episodes", 1, "--no-score", "--out", tmp_path / "e.json")
    line = _one_error_line(err)
    assert code == 2 and "missing" in line
    for part in missing:
        assert str(tmp_path / f"ppo_tc{part}") in line
    assert not (tmp_path / "e.json").exists()


def test_trusted_zip_without_its_normalization_or_metadata_is_an_error(own_run):
    folder, _, _ = own_run
    (folder / "vecnormalize.pkl").unlink()
    with pytest.raises(PolicyFileError, match="no normalization file: expected .*vecnormalize.pkl"):
        load_policy(folder / "model.zip", trust_pickle=True)
    (folder / "progress.json").unlink()
    with pytest.raises(PolicyFileError, match="no metadata: expected .*progress.json"):
        load_policy(folder / "model.zip", trust_pickle=True)


# ------------------------------------------------------------------------------------------ broken files
def _flip_last_bytes(path: Path, n: int = 64) -> None:
    data = bytearray(path.read_bytes())
    data[-n:] = bytes(b ^ 0xFF for b in data[-n:])
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["weights blob", "weights header", "truncated weights", "truncated npz",
                                    "garbage json"])
def test_broken_policy_files_are_one_line_naming_the_file(tmp_path, capsys, damage):
    stem = _copy_shipped(tmp_path)
    weights, npz, meta = (tmp_path / f"ppo_tc{p}" for p in (".safetensors", "_vecnormalize.npz", ".json"))
    if damage == "weights blob":  # the tensors' bytes: only the checksum tells
        _flip_last_bytes(weights)
        bad = weights
    elif damage == "weights header":
        weights.write_bytes(b"\xff" * 8 + weights.read_bytes()[8:])
        _reseal(stem, "weights", weights)
        bad = weights
    elif damage == "truncated weights":
        weights.write_bytes(weights.read_bytes()[:1000])
        _reseal(stem, "weights", weights)
        bad = weights
    elif damage == "truncated npz":
        npz.write_bytes(npz.read_bytes()[:300])
        _reseal(stem, "normalization", npz)
        bad = npz
    else:
        meta.write_text('{"format": "wl-ppo-pol')
        bad = meta
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", stem, "--episodes", 1, "--no-score",
                        "--out", tmp_path / "e.json")
    assert code == 2 and str(bad) in _one_error_line(err)


@pytest.mark.parametrize("damage", ["policy.pth", "truncated pkl", "truncated zip"])
def test_broken_trusted_files_are_one_line_naming_the_file(own_run, capsys, tmp_path, damage):
    folder, _, _ = own_run
    zip_path = folder / "model.zip"
    if damage == "policy.pth":  # a valid zip whose weights entry is garbage
        with zipfile.ZipFile(zip_path) as z:
            entries = {n: z.read(n) for n in z.namelist()}
        entries["policy.pth"] = b"not a torch file" * 10
        with zipfile.ZipFile(zip_path, "w") as z:
            for name, data in entries.items():
                z.writestr(name, data)
        bad = zip_path
    elif damage == "truncated pkl":
        pkl = folder / "vecnormalize.pkl"
        pkl.write_bytes(pkl.read_bytes()[:100])
        bad = pkl
    else:
        zip_path.write_bytes(zip_path.read_bytes()[:500])
        bad = zip_path
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", zip_path, "--trust-pickle",
                        "--episodes", 1, "--no-score", "--out", tmp_path / "e.json")
    assert code == 2 and str(bad) in _one_error_line(err)


# ------------------------------------------------------------------------------------------ controllers
BAD_CONTROLLERS = '''
import sys, time
import numpy as np
from agents.operator import OperatorPolicy


class _Base:
    fail_at = (0, 3)  # (episode, step)

    def __init__(self, braking="service"):
        self.inner, self.episode, self.step = OperatorPolicy(braking), -1, 0

    def reset(self):
        self.episode, self.step = self.episode + 1, 0

    def act(self, obs):
        action = self.inner.act(obs)
        if (self.episode, self.step) == self.fail_at:
            action = self.bad(action)
        self.step += 1
        return action


class Raises(_Base):
    def bad(self, action):
        return 1 / 0

class ReturnsDict(_Base):
    def bad(self, action):
        return {"fuel": 1.0}

class WrongShape(_Base):
    def bad(self, action):
        return action[:3]

class Strings(_Base):
    def bad(self, action):
        return ["1", "0", "0", "0"]

class Ragged(_Base):
    def bad(self, action):
        return [[1.0], [1.0, 2.0]]

class NaNSecondEpisode(_Base):
    fail_at = (1, 5)
    def bad(self, action):
        return np.array([np.nan, 0, 0, 0])

class Exits(_Base):
    def bad(self, action):
        sys.exit(0)

class ExitsOnCreation:
    def __init__(self):
        sys.exit(0)

class ResetRaises(_Base):
    def reset(self):
        raise KeyError("plan")

class Sleeps(_Base):
    def bad(self, action):
        try:
            time.sleep(30)
        except Exception:  # a broad handler must not swallow the timeout
            pass
        return action

class Spins(_Base):
    def bad(self, action):
        while True:
            pass

class Outer:
    class Inner(_Base):
        pass
'''


@pytest.fixture
def bad_module(tmp_path: Path) -> Path:
    path = tmp_path / "bad_controllers.py"
    path.write_text(BAD_CONTROLLERS)
    return path


@pytest.mark.parametrize("cls, where, needle", [
    ("Raises", "episode 0, step 3", "ZeroDivisionError"),
    ("ReturnsDict", "episode 0, step 3", "returned {'fuel': 1.0} (dict), not 4 numbers"),
    ("WrongShape", "episode 0, step 3", "shape (3,), expected (4,)"),
    ("Strings", "episode 0, step 3", "not 4 numbers"),
    ("Ragged", "episode 0, step 3", "not 4 numbers"),
    ("NaNSecondEpisode", "episode 1, step 5", "non-finite action [nan, 0.0, 0.0, 0.0]"),
    ("Exits", "episode 0, step 3", "sys.exit(0)"),
    ("ResetRaises", "episode 0, step 0", "reset() failed"),
])
def test_misbehaving_controller_is_one_line_naming_it_the_episode_and_step(tmp_path, capsys, bad_module, cls, where,
                                                                            needle):
    spec = f"{bad_module}:{cls}"
    out = tmp_path / "e.json"
    code, _, err = _run(capsys, "evaluate", "--controller", spec, "--episodes", 2, "--no-score", "--out", out)
    line = _one_error_line(err)
    assert code == 2 and f"controller {spec}" in line and where in line and needle in line
    assert not out.exists()


def test_controller_exiting_on_creation_is_an_error(tmp_path, capsys, bad_module):
    code, _, err = _run(capsys, "evaluate", "--controller", f"{bad_module}:ExitsOnCreation", "--no-score",
                        "--out", tmp_path / "e.json")
    assert code == 2 and "sys.exit(0)" in _one_error_line(err) and not (tmp_path / "e.json").exists()


@pytest.mark.parametrize("cls", ["Sleeps", "Spins"])
def test_act_timeout_interrupts_a_hanging_act(tmp_path, capsys, bad_module, cls):
    import signal
    import time

    before = signal.getsignal(signal.SIGALRM)
    t0 = time.monotonic()
    code, _, err = _run(capsys, "evaluate", "--controller", f"{bad_module}:{cls}", "--act-timeout", 0.3,
                        "--episodes", 1, "--no-score", "--out", tmp_path / "e.json")
    assert time.monotonic() - t0 < 10.0
    line = _one_error_line(err)
    assert code == 2 and "within the act timeout of 0.3 s" in line and "episode 0, step 3" in line
    assert signal.getsignal(signal.SIGALRM) == before  # the handler is restored


def test_act_timeout_leaves_a_well_behaved_controller_alone(tmp_path, capsys):
    from agents.evaluate import evaluate_controller
    from agents.operator import OperatorPolicy

    plain = evaluate_controller(OperatorPolicy("tc"), "tc", episodes=2, score=False)
    timed = evaluate_controller(OperatorPolicy("tc"), "tc", episodes=2, score=False, act_timeout=5.0)
    assert plain == timed and plain["summary"]["completion_rate"] == 1.0
    code, out, err = _run(capsys, "evaluate", "--help")
    assert "--act-timeout" in out and "default: off" in " ".join(out.split())
    for bad in ("-1", "nan", "0", "1e308"):  # (1e308 overflowed the timer: an error blamed on the controller)
        code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--act-timeout", bad, "--no-score",
                            "--out", tmp_path / "e.json")
        assert code == 2 and "--act-timeout" in _one_error_line(err) and not (tmp_path / "e.json").exists()


@pytest.mark.parametrize("kw, needle", [
    ({"episodes": "3"}, "episodes must be an integer in [1, 100000], got '3'"),  # was a TypeError
    ({"episodes": 10**20}, "episodes must be an integer in [1, 100000]"),  # was an OverflowError
    ({"act_timeout": 1e308}, "act_timeout (--act-timeout) must be a number of seconds in (0, 86400]"),
    ({"target_ratio": 10**400}, "target_ratio must lie in [1, 3]"),
    # (an AttributeError on .braking before; dicts and JSON are now taken, as the env takes them)
    ({"scenarios": {"payload": 7000.0}}, "scenarios must be a list of scenarios"),
    ({"init_noise": True}, "init_noise must lie in [0, 1]"),  # (taken as 1.0)
    ({"scenario": 5}, "scenario must be a Scenario"),
    ({"scenarios": [{"payload": 1.0, "braking": "tc"}]}, "Scenario.payload must lie in"),
    # (each was a bare TypeError or gymnasium error from gym.make, or silently overridden / accepted)
    ({"env_kwargs": {"foo": 1}}, "env_kwargs: WheelLoader-v2 takes no argument(s) ['foo']"),
    ({"env_kwargs": "x"}, "env_kwargs must be a dict"),
    ({"env_kwargs": {"braking": "service"}}, "contradicts the evaluation's braking 'tc'"),
    ({"env_kwargs": {"init_noise": 0.5}}, "env_kwargs sets init_noise"),
    ({"env_id": "Foo-v0"}, "env_id must be one of WheelLoader-v1"),
    ({"env_id": 5}, "env_id must be one of"),
    ({"unknown": "ignore"}, "unknown must be 'raise' or 'skip'"),
    ({"progress": 5}, "progress must be a function"),
])
def test_evaluation_settings_are_checked_by_name(kw, needle):
    from agents.evaluate import evaluate_controller
    from agents.operator import OperatorPolicy

    with pytest.raises(ValueError) as exc:
        evaluate_controller(OperatorPolicy("tc"), "tc", score=False, **kw)
    assert needle in str(exc.value)


def test_numpy_scalar_settings_are_the_numbers_they_hold():
    """np.int64(1) episodes was refused as "must be an integer in [1, 100000], got np.int64(1)" (the env takes
    numpy scalars)."""
    from agents.evaluate import evaluate_controller
    from agents.operator import OperatorPolicy

    r = evaluate_controller(OperatorPolicy("tc"), "tc", episodes=np.int64(2), init_noise=np.float32(0.5),
                            seed=np.int64(3), score=False)
    plain = evaluate_controller(OperatorPolicy("tc"), "tc", episodes=2, init_noise=0.5, seed=3, score=False)
    assert [e["T"] for e in r["per_episode"]] == [e["T"] for e in plain["per_episode"]]


def test_user_classes_resolve_by_dotted_name(bad_module):
    from agents.evaluate import load_controller

    assert type(load_controller(f"{bad_module}:Outer.Inner", "tc")).__name__ == "Inner"
    assert load_controller("agents.operator:OperatorPolicy", "tc").braking == "tc"
    with pytest.raises(ValueError, match="defines no 'Nope'"):
        load_controller(f"{bad_module}:Nope", "tc")
    with pytest.raises(ValueError, match="cannot import no_such_module_xyz"):
        load_controller("no_such_module_xyz:Driver", "tc")


# ------------------------------------------------------------------------------------------ logging
def test_warnings_of_the_agents_reach_the_cli_through_logging(tmp_path, capsys, caplog):
    import logging

    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", POLICIES / "ppo_tc", "--braking",
                        "service", "--episodes", 1, "--no-score", "--out", tmp_path / "e.json")
    assert code == 0 and "warning: the policy" in err and "trained with tc braking, evaluated with service" in err
    record = next(r for r in caplog.records if "trained with tc braking" in r.getMessage())
    assert record.name == "agents.evaluate" and record.levelno == logging.WARNING


# ------------------------------------------------------------------------------------------ run folders
def _checkpointed_run(tmp_path: Path) -> PPOConfig:
    """A tiny run stopped after its first checkpoints (as a kill would leave it)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from agents.ppo import train

    class Stop(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps >= 2048:
                raise KeyboardInterrupt
            return True

    cfg = PPOConfig(num_envs=4, n_steps=64, batch_size=64, net_arch=(8,), total_timesteps=4096, eval_freq=10**6,
                    checkpoint_freq=1024, score=False, progress_bar=False, log_dir=str(tmp_path), run_name="r")
    with pytest.raises(KeyboardInterrupt):
        train(cfg, callbacks=[Stop()])
    return cfg


def test_a_checkpoint_restores_the_model_exactly_and_holds_no_pickle(tmp_path):
    """What resuming loads is what was saved: the weights, Adam's moments and settings, the update count and the
    normalization's running statistics, bit for bit; and the checkpoint holds no pickle."""
    from agents.ppo import latest_checkpoint, restore_checkpoint, save_checkpoint

    cfg = PPOConfig(num_envs=2, n_steps=32, batch_size=32, net_arch=(8,), score=False, progress_bar=False,
                    log_dir=str(tmp_path), run_name="x")
    env = make_env(cfg)
    model = build_model(cfg, env, tmp_path / "tb")
    model.learn(128)  # (the optimizer has state, the statistics have moved)
    folder = save_checkpoint(model, env, tmp_path / "run" / "checkpoints" / "step_0000000128", {"num_timesteps": 128, "wall_time": 1.0})
    assert latest_checkpoint(tmp_path / "run") == folder
    assert not [p for p in folder.iterdir() if p.suffix in (".zip", ".pkl")]
    env2 = make_env(cfg, seed=7)
    fresh = build_model(cfg, env2, tmp_path / "tb2")
    restore_checkpoint(fresh, env2, folder)
    for (k, a), (_, b) in zip(model.policy.state_dict().items(), fresh.policy.state_dict().items(), strict=True):
        assert np.array_equal(a.numpy(), b.numpy()), k
    s1, s2 = model.policy.optimizer.state_dict(), fresh.policy.optimizer.state_dict()
    assert s1["param_groups"] == s2["param_groups"] and s1["state"].keys() == s2["state"].keys()
    for i in s1["state"]:
        for name in s1["state"][i]:
            assert np.array_equal(np.asarray(s1["state"][i][name]), np.asarray(s2["state"][i][name])), (i, name)
    assert fresh._n_updates == model._n_updates > 0
    for name in ("obs_rms", "ret_rms"):
        a, b = getattr(env, name), getattr(env2, name)
        assert np.array_equal(a.mean, b.mean) and np.array_equal(a.var, b.var) and a.count == b.count


def test_resuming_never_unpickles_and_refuses_bad_run_files(tmp_path, marker):
    """A run folder is resumed from its pickle-free files only: pickles planted in its checkpoint never run. Its
    config.json, progress.json and latest.json are checked, each error naming the file; a pointer to a folder
    outside the checkpoints is passed over."""
    from agents.ppo import CheckpointError, latest_checkpoint, train

    cfg = _checkpointed_run(tmp_path)
    ckpt = latest_checkpoint(cfg.run_dir)
    _evil_sb3_zip(ckpt / "model.zip", marker)
    (ckpt / "vecnormalize.pkl").write_bytes(_evil_pickle(marker))
    config, progress, pointer = cfg.run_dir / "config.json", ckpt / "progress.json", cfg.run_dir / "checkpoints" / "latest.json"
    good = {f: f.read_text() for f in (config, progress)}
    named = PPOConfig(log_dir=cfg.log_dir, run_name="r", progress_bar=False)
    for bad in ("{}", "[1]", "not json", json.dumps({"config": {"seed": -1}})):
        config.write_text(bad)
        with pytest.raises(ValueError, match="config.json is not a readable run config"):
            train(named, resume=True)
    config.write_text(good[config])
    for bad in ({}, {"num_timesteps": "2048", "wall_time": 1.0}, {"num_timesteps": -5, "wall_time": 1.0},
                {"num_timesteps": 1024, "wall_time": float("nan")}, {"num_timesteps": 10**23, "wall_time": 1.0},
                {"num_timesteps": 1024, "wall_time": 10**400}):  # (a seed error; an OverflowError's traceback)
        progress.write_text(json.dumps(bad))
        with pytest.raises(CheckpointError, match="progress.json"):
            train(named, resume=True)
        assert config.read_text() == good[config]  # (a failed resume records no command)
    progress.write_text(good[progress])
    eval_csv = cfg.run_dir / "eval.csv"
    good_eval = eval_csv.read_bytes()
    for bad in (b"step,a\nabc,1\n", b"\xff\xfe,a\n"):
        eval_csv.write_bytes(bad)
        with pytest.raises(ValueError, match="eval.csv cannot be continued"):
            train(named, resume=True)
        assert config.read_text() == good[config]
    eval_csv.write_bytes(good_eval)
    training = (ckpt / "training.json").read_text()
    for bad in ({"optimizer": {"param_groups": [{"lr": "exec"}], "scalars": {}}},
                {"optimizer": {"param_groups": [{"lr": 10**400}], "scalars": {}}},  # (an OverflowError's traceback)
                {**json.loads(training), "n_updates": 10**400}):
        (ckpt / "training.json").write_text(json.dumps(bad))
        with pytest.raises(CheckpointError, match=f"checkpoint {ckpt}"):
            train(named, resume=True)
    pointer.write_text(json.dumps({"checkpoint": "../../r"}))
    assert latest_checkpoint(cfg.run_dir) == ckpt  # (the pointer names no checkpoint folder: the newest one is taken)
    assert not marker.exists()


def test_an_older_pickled_checkpoint_is_refused_by_name(tmp_path, marker):
    from agents.ppo import CheckpointError, latest_checkpoint

    old = tmp_path / "run" / "checkpoints" / "step_0000001024"
    old.mkdir(parents=True)
    _evil_sb3_zip(old / "model.zip", marker)
    (old / "progress.json").write_text(json.dumps({"num_timesteps": 1024, "wall_time": 1.0}))
    with pytest.raises(CheckpointError, match="older checkpoint .*pickle.* does not resume from"):
        latest_checkpoint(tmp_path / "run")
    assert not marker.exists()


def test_a_run_is_not_saved_with_settings_its_env_refuses(tmp_path):
    """The env's checks run before config.json is written; a run stopped before its first checkpoint starts again
    with the settings given now (agents.seeds)."""
    from agents.ppo import train
    from agents.seeds import run_state

    cfg = PPOConfig(w_fuel=1e7, score=False, progress_bar=False, log_dir=str(tmp_path), run_name="bad")
    with pytest.raises(ValueError, match="RewardConfig.w_fuel must lie in"):  # (the env's range, not the config's)
        train(cfg)
    assert not (cfg.run_dir / "config.json").exists()
    cfg.run_dir.mkdir(parents=True)
    (cfg.run_dir / "config.json").write_text(json.dumps({"config": cfg.to_dict() | {"w_fuel": 0.5}}))
    assert run_state(cfg) == "new"
    with pytest.raises(ValueError, match="seed must be an integer in \\[0, 2\\*\\*31 - 1\\]"):
        PPOConfig(seed=2**40)


def test_a_failed_resume_on_a_bad_checkpoint_changes_nothing(tmp_path):
    """A checkpoint whose policy file was cut short failed the resume by name, but config.json had the failed
    command and eval.csv was rewritten (its line endings changed) (stop 59)."""
    from agents.ppo import CheckpointError, latest_checkpoint, train

    cfg = _checkpointed_run(tmp_path)
    ckpt = latest_checkpoint(cfg.run_dir)
    with open(ckpt / "policy.safetensors", "r+b") as f:
        f.truncate(100)
    eval_csv = cfg.run_dir / "eval.csv"
    eval_csv.write_bytes(eval_csv.read_bytes().replace(b"\n", b"\r\n"))
    before = {f: f.read_bytes() for f in (cfg.run_dir / "config.json", eval_csv)}
    with pytest.raises((CheckpointError, PolicyFileError), match="sha256 differs|policy"):
        train(PPOConfig(log_dir=cfg.log_dir, run_name="r", progress_bar=False), resume=True, command="wl train --resume")
    assert {f: f.read_bytes() for f in before} == before


def test_an_interrupted_checkpoint_leaves_no_staging_folder(tmp_path, monkeypatch):
    """SIGTERM (or Ctrl-C) while a checkpoint was staged left checkpoints/.step_*.tmp until the next resume; and
    `wl train` exited 130 on SIGTERM, not 143 (stop 59)."""
    import agents.ppo as ppo
    import agents.train_cli as train_cli
    from mpc import interrupt

    cfg = PPOConfig(num_envs=2, n_steps=8, batch_size=16, net_arch=(8,), score=False, progress_bar=False,
                    log_dir=str(tmp_path), run_name="s")
    env = ppo.make_env(cfg)
    env.reset()
    model = ppo.build_model(cfg, env, tmp_path / "tb")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ppo, "write_json_atomic", killed)
    folder = tmp_path / "checkpoints" / "step_1"
    with pytest.raises(KeyboardInterrupt):
        ppo.save_checkpoint(model, ppo._vecnorm_of(env), folder, {"num_timesteps": 0, "wall_time": 0.0})
    assert not folder.exists() and list((tmp_path / "checkpoints").iterdir()) == []

    def terminated(*args, **kwargs):
        import signal

        interrupt._handler(signal.SIGTERM, None)  # (as the handler `wl` installs does on SIGTERM)

    monkeypatch.setattr(ppo, "train", terminated)
    parser = argparse.ArgumentParser()
    train_cli.add_train_args(parser)
    ns = parser.parse_args(["--log-dir", str(tmp_path), "--run-name", "t"])
    with interrupt.handling():
        assert train_cli.run_train(ns, "wl train", "wl train") == 143
