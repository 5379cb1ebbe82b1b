"""A controller in ``WheelLoader-v2`` (or its ``env_id``) scored against the optimal control benchmark (``wl evaluate``, ``wl run``).

* :func:`load_controller` - ``"ppo"``, ``"operator"``, ``"mpc"`` or a user's ``"module:Class"`` /
  ``"path/to/file.py:Class"`` as a :class:`wl_env.controller.Controller`.
* :func:`evaluate_controller` - episodes through :func:`wl_env.rollout.run_episode`: the nominal start
  (episode 0, the one the optimum is computed for) and perturbed starts (episodes 1..N-1, seeded
  ``seed + i``); per episode and aggregated: success (cycle completed, end targets met), cycle time,
  fuel, constraint violation, and the score of :func:`mpc.benchmark.scoring.score_run` (time gap to the minimum
  cycle time, fuel gap to the Pareto fuel at the same cycle time).
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
import logging
import math
import os
import pkgutil
import signal
import sys
import threading
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from agents.ppo_config import MAX_SEED, PLAN_ENV_IDS
from mpc import interrupt
from wl_env import cycle
from wl_env.atomic_io import check_output_folder
from wl_env.controller import Controller
from wl_env.params import LoaderParams, check_flag, plain, shown
from wl_env.scenario import Scenario, resolve_scenario

log = logging.getLogger(__name__)

BUILTIN_CONTROLLERS = ("ppo", "plan", "bc", "operator", "mpc")
POLICY_DIR = Path(__file__).resolve().parent / "policies"
# the shipped policies: PPO on the paper's cycle (WheelLoader-v1), and the target-conditioned PPO and
# behaviour-cloned (imitation) policies of the target task (the env each was trained on is in its metadata)
SHIPPED_POLICIES = {"ppo": "ppo_{braking}", "ppo-target": "ppo_target_{braking}", "plan": "plan_target_{braking}",
                    "bc": "bc_target_{braking}"}


def default_policy_path(braking: str, kind: str = "ppo") -> Path:
    """The weights file of a shipped policy of a braking alternative (with its ``_vecnormalize.npz`` and
    ``.json`` beside it, :mod:`agents.policy_files`); ``kind`` one of :data:`SHIPPED_POLICIES`."""
    if kind not in SHIPPED_POLICIES:
        raise ValueError(f"kind must be one of {', '.join(SHIPPED_POLICIES)}, got {kind!r}")
    return POLICY_DIR / f"{SHIPPED_POLICIES[kind].format(braking=cycle.check_braking(braking))}.safetensors"


# ---------------------------------------------------------------------------------------------- loading
def load_controller(spec: str, braking: str, model: str | None = None, *, trust_pickle: bool = False,
                    scenario: Scenario | None = None, targeted: bool = False) -> Controller:
    """The controller named by ``spec`` for ``braking``.

    ``"ppo"`` loads ``model`` (default: the shipped ``agents/policies/ppo_<braking>``, trained on the paper's
    cycle, or with ``targeted`` (an evaluation at target cycle times) the target-conditioned
    ``ppo_target_<braking>``; a pickle-free policy, or with ``trust_pickle`` a stable-baselines3 zip you
    trust, see :func:`agents.ppo.load_policy`); ``"plan"`` the target-conditioned PPO of one plan per cycle
    (``plan_target_<braking>``, WheelLoaderPlan-v1) or ``model``; ``"bc"`` the imitation baseline ``bc_target_<braking>``
    (behaviour cloning of the MPC, :mod:`agents.imitation`, then PPO fine-tuning) or ``model``; ``"operator"``
    is the rule-based driver, ``"mpc"`` the minimum-time MPC. ``"module:Class"`` or
    ``"path/to/file.py:Class"`` imports the class (or factory) and calls it with ``braking=`` if it takes
    that argument (and ``model=`` if a model is given), else without arguments; the result needs an
    ``act(obs)`` method (``reset()`` is optional for :func:`wl_env.rollout.run_episode`). ``scenario``: the
    cycle the operator and the MPC start with (and a user's class, if it takes ``scenario=``); during an
    evaluation each episode's reaches a controller whose ``reset`` takes ``scenario=``.
    """
    cycle.check_braking(braking)
    if not isinstance(spec, str):
        raise ValueError(f"the controller must be named by a string ({', '.join(BUILTIN_CONTROLLERS)}, module:Class or "
                         f"path/to/file.py:Class), got {type(spec).__name__}")
    if model is not None and not isinstance(model, (str, os.PathLike)):
        raise ValueError(f"model must be a policy file's path or None, got {type(model).__name__}")
    if scenario is not None:  # (a dict or JSON, as evaluate_controller takes them; anything else named)
        scenario = resolve_scenario(scenario, braking)
    spec = spec.strip()
    if model is not None and not str(model).strip():  # (Path("") is the working folder: it searched there)
        raise ValueError("--model must name a policy (PATH.safetensors, ...), got an empty string")
    if spec in ("ppo", "plan", "bc"):
        kind = spec if spec in ("plan", "bc") else "ppo-target" if targeted else "ppo"
        return _load_ppo(braking, model, trust_pickle, kind)
    if trust_pickle:
        raise ValueError(f"--trust-pickle is for --controller ppo, plan or bc (the policy file it loads), not {spec!r}")
    if spec in ("operator", "mpc") and model is not None:
        raise ValueError(f"--model is for learned controllers (ppo, module:Class), not {spec!r}")
    if spec == "operator":
        from agents.operator import OperatorPolicy

        return OperatorPolicy(braking, params=None if scenario is None else scenario.params())
    if spec == "mpc":
        from mpc.controller.mpc import MPCController

        return MPCController(braking, params=None if scenario is None else scenario.params())
    if ":" not in spec:
        raise ValueError(f"unknown controller {spec!r}: use {', '.join(BUILTIN_CONTROLLERS)}, module:Class "
                         f"or path/to/file.py:Class")
    return _load_user_controller(spec, braking, model, scenario)


def controller_files(spec: str, braking: str, model: str | os.PathLike | None = None, *,
                     targeted: bool = False) -> list[Path]:
    """The files :func:`load_controller` may read for these arguments (whether they exist or not): a user's
    ``file.py``, and the policy's files with every companion it looks for (pickle-free, or a stable-baselines3 zip's).
    An output must be none of them: ``wl evaluate --model P --out P.json`` wrote the result over P's metadata."""
    spec = spec.strip() if isinstance(spec, str) else ""
    target = spec.rpartition(":")[0]
    files = [Path(target).expanduser()] if target.endswith(".py") or "/" in target or os.sep in target else []
    if spec in ("ppo", "plan", "bc") and model is None:
        kind = spec if spec in ("plan", "bc") else "ppo-target" if targeted else "ppo"
        model = default_policy_path(braking, kind)
    return files if model is None or not str(model).strip() else files + policy_input_files(model)


def policy_input_files(model: str | os.PathLike) -> list[Path]:
    """The files loading the policy ``model`` (a pickle-free policy's stem or file, a stable-baselines3 zip, or a
    run folder) may read, with every companion it looks for, whether they exist or not."""
    from agents.policy_files import PolicyFiles

    def three(stem: Path) -> list[Path]:
        f = PolicyFiles.of(stem)
        return [f.weights, f.normalization, f.metadata]

    p = Path(model).expanduser()
    sb3 = ("model.zip", "vecnormalize.pkl", "summary.json", "progress.json")
    if p.is_dir():
        return [f for base in (p, p / "final") for f in (*three(base / "policy"), *(base / name for name in sb3))]
    stem = p.with_suffix("") if p.suffix in (".zip", ".pkl") else p
    return [p, *three(p), stem.with_name(stem.name + ".json"), stem.with_name(stem.name + "_vecnormalize.pkl"),
            *(p.parent / name for name in sb3)]


def _load_ppo(braking: str, model: str | None, trust_pickle: bool = False, kind: str = "ppo") -> Controller:
    path = Path(model).expanduser() if model is not None else default_policy_path(braking, kind)
    if model is None and not path.exists():
        how = {"ppo": f"wl train --braking {braking} --export PATH",
               "ppo-target": f"wl train --braking {braking} --env-id WheelLoaderTarget-v6 --scenario train --export PATH",
               "plan": f"python scripts/train_plan_policy.py --braking {braking} --export PATH",
               "bc": f"python scripts/train_bc.py --braking {braking} --export PATH"}[kind]
        raise FileNotFoundError(f"no shipped policy at {path} (make one with `{how}`, then pass --model PATH)")
    from agents.ppo import load_policy

    policy = load_policy(path, trust_pickle=trust_pickle)
    if kind == "plan" and policy.env_id not in PLAN_ENV_IDS:  # (a per-step policy ran, reported as the plan policy)
        raise ValueError(f"--model {path} is a policy of {policy.env_id}, not of a plan env: --controller ppo runs it")
    if policy.braking not in (None, braking):
        # Allowed (a cross-evaluation is a legitimate experiment), but usually a mix-up.
        log.warning("the policy %s was trained with %s braking, evaluated with %s", path, policy.braking, braking)
    return policy


def _load_user_controller(spec: str, braking: str, model: str | None, scenario: Scenario | None = None) -> Controller:
    target, _, name = spec.rpartition(":")
    if not target or not all(part.isidentifier() for part in name.split(".")):
        raise ValueError(f"controller {spec!r}: expected module:Class or path/to/file.py:Class")
    is_file = target.endswith(".py") or "/" in target or os.sep in target
    if is_file:
        # pkgutil.resolve_name imports by module name only: a file is imported here under a unique name first.
        factory = _resolve(_import_file(target, spec).__name__, name, spec, target)
    else:
        _cwd_on_path()
        factory = _resolve(target, name, spec, target)
    if not callable(factory):
        raise ValueError(f"controller {spec!r}: {name} is not a class or factory")
    kwargs: dict[str, Any] = {}
    if _accepts(factory, "braking"):
        kwargs["braking"] = braking
    if scenario is not None and _accepts(factory, "scenario"):
        kwargs["scenario"] = scenario
    if model is not None:
        if not _accepts(factory, "model"):
            raise ValueError(f"--model given, but controller {spec!r} takes no model= argument")
        kwargs["model"] = model
    try:
        controller = factory(**kwargs)
    except (Exception, SystemExit) as exc:  # a user's sys.exit() must not end wl evaluate quietly
        raise ValueError(f"controller {spec!r}: {name}({', '.join(f'{k}={v!r}' for k, v in kwargs.items())}) "
                         f"failed: {_brief(exc)}") from exc
    if not callable(getattr(controller, "act", None)):
        raise ValueError(f"controller {spec!r}: {name} has no act(obs) method")
    return controller


def _resolve(module: str, name: str, spec: str, target: str) -> Any:
    """``module:name`` by :func:`pkgutil.resolve_name` (imports the module, follows a dotted name)."""
    try:
        return pkgutil.resolve_name(f"{module}:{name}")
    except AttributeError as exc:
        if module in sys.modules:  # imported; the name is not in it
            raise ValueError(f"controller {spec!r}: {target} defines no {name!r}") from None
        raise ValueError(f"controller {spec!r}: cannot import {target}: {_brief(exc)}") from exc
    except (Exception, SystemExit) as exc:
        raise ValueError(f"controller {spec!r}: cannot import {target}: {_brief(exc)}") from exc


def _brief(exc: BaseException) -> str:
    if isinstance(exc, SystemExit):
        return f"it called sys.exit({exc.code!r})"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:200] + ' ...' if len(text) > 200 else text}"


def _accepts(factory: Callable[..., Any], arg: str) -> bool:
    try:
        sig = inspect.signature(factory)
    except (TypeError, ValueError):  # some builtins have no signature: call them without arguments
        return False
    return any(p.kind is p.VAR_KEYWORD or (p.name == arg and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY))
               for p in sig.parameters.values())


def _cwd_on_path() -> None:
    # The console script `wl` does not put the working directory on sys.path (python -m would):
    # append it, so a user's module beside them imports, without shadowing installed packages.
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())


def _import_file(target: str, spec: str) -> ModuleType:
    path = Path(target).expanduser()
    try:  # (a name too long for the system was a bare OSError naming no option)
        folder, regular = path.is_dir(), path.is_file()
    except OSError as exc:
        raise ValueError(f"controller file {path} cannot be read: {exc.strerror or exc} (from --controller {spec})") from None
    if folder:  # (it said "no controller file /tmp", for a folder that is there)
        raise IsADirectoryError(f"controller file {path} is a folder, not a Python file (from --controller {spec})")
    if not regular:
        raise FileNotFoundError(f"no controller file {path} (from --controller {spec})")
    path = path.resolve()
    # A unique module name per file: two controllers named alike in different folders do not collide.
    name = f"wl_user_{path.stem}_{hashlib.sha1(str(path).encode()).hexdigest()[:10]}"
    module_spec = importlib.util.spec_from_file_location(name, path)
    if module_spec is None or module_spec.loader is None:
        raise ValueError(f"controller {spec!r}: {path} is not a Python module")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module  # dataclasses and pickle look classes up by module name
    if str(path.parent) not in sys.path:
        sys.path.append(str(path.parent))  # its sibling imports work as when run as a script
    try:
        module_spec.loader.exec_module(module)
    except (Exception, SystemExit) as exc:
        del sys.modules[name]
        raise ValueError(f"controller {spec!r}: importing {path} failed: {_brief(exc)}") from exc
    return module


# ---------------------------------------------------------------------------------------------- guard
class ControllerError(RuntimeError):
    """A controller failed during an episode: it raised, exited, returned a bad action or took too long.
    The message is one line naming the controller, the episode and the step."""


class _ActTimeout(BaseException):
    """Raised by SIGALRM in a late act(); not an Exception, so the controller's own ``except Exception``
    does not swallow it."""


_alarm_fired = threading.Event()  # (the timer's raise inside a library may come back as another exception)


def _on_alarm(signum: int, frame: Any) -> None:
    _alarm_fired.set()
    raise _ActTimeout


class GuardedController:
    """``controller`` as :func:`wl_env.rollout.run_episode` drives it, with every call checked: an exception,
    ``sys.exit()``, an action that is not ``n_actions`` finite numbers (4; WheelLoaderTarget-v2's driver: 3) or (with ``act_timeout``) an ``act()`` slower
    than ``act_timeout`` seconds is a :class:`ControllerError` naming ``name``, the episode and the step.

    The timeout is a SIGALRM timer (``signal.setitimer``) around each ``act()`` on the main thread: it
    interrupts Python code and sleeps, not a C extension call that never returns to the interpreter.
    """

    def __init__(self, controller: Controller, name: str, act_timeout: float | None = None, n_actions: int = 4) -> None:
        self.controller, self.name, self.act_timeout, self.n_actions = controller, name, act_timeout, n_actions
        self.episode, self.step = -1, 0

    def takes_target(self) -> bool:
        from wl_env.rollout import takes_target

        return takes_target(self.controller)

    def reset(self, scenario: Scenario | None = None, target_time: float | None = None) -> None:
        from wl_env.rollout import check_takes_target, reset_controller

        self.episode, self.step = self.episode + 1, 0
        if target_time is not None:  # refused by name, not as the controller's own error
            check_takes_target(self.controller)
        if hasattr(self.controller, "reset"):
            self._call("reset()", lambda: reset_controller(self.controller, scenario, target_time), timeout=None)

    def act(self, obs: np.ndarray) -> np.ndarray:
        out = self._call("act()", self.controller.act, obs, timeout=self.act_timeout)
        if isinstance(out, np.ma.MaskedArray) and np.ma.is_masked(out):  # (asarray read the values under the mask)
            self._fail(f"act() returned a masked array with {np.ma.count_masked(out)} masked entries, not "
                       f"{self.n_actions} numbers")
        try:
            raw = np.asarray(out) if isinstance(out, (np.ndarray, list, tuple)) or hasattr(out, "__array__") else None
        except Exception:  # noqa: BLE001 - ragged lists, tensors that refuse conversion
            raw = None
        names = "[engine-speed request, bucket, braking fraction]" if self.n_actions == 3 else "[fuel, bucket, brake, shift]"
        if raw is None or raw.dtype.kind not in "iuf":
            self._fail(f"act() returned {_short(out)} ({type(out).__name__}), not {self.n_actions} numbers {names}")
        if raw.shape != (self.n_actions,):
            self._fail(f"act() returned an action of shape {raw.shape}, expected ({self.n_actions},) {names}")
        action = raw.astype(np.float64)
        if not np.all(np.isfinite(action)):
            self._fail(f"act() returned a non-finite action {action.tolist()}")
        self.step += 1
        return action

    def _where(self) -> str:
        return f"episode {self.episode}, step {self.step}"

    def _fail(self, what: str) -> None:
        raise ControllerError(f"controller {self.name}: {what} at {self._where()}")

    def _call(self, what: str, fn: Callable[..., Any], *args: Any, timeout: float | None) -> Any:
        timed_out = False
        try:
            if timeout is None:
                out = fn(*args)
            else:
                _alarm_fired.clear()
                signal.setitimer(signal.ITIMER_REAL, timeout)
                try:
                    out = fn(*args)
                finally:
                    signal.setitimer(signal.ITIMER_REAL, 0.0)
        except _ActTimeout:
            raise self._timed_out(what, timeout) from None
        except KeyboardInterrupt:
            # (the timer inside IPOPT: CasADi returns an aborted solve, which the MPC raises as an interrupt; measured,
            # `wl evaluate --controller mpc --act-timeout 1` exited 130 "interrupted")
            if not (timeout is not None and _alarm_fired.is_set() and not interrupt.interrupted()):
                raise
            timed_out = True  # (raised below, outside this handler: an error whose context is a KeyboardInterrupt
            # is what Ctrl-C became, to the command line's interrupt.caused_by_interrupt)
        except (Exception, SystemExit) as exc:  # SystemExit: a user's sys.exit() must not end wl evaluate quietly
            interrupt.check()  # (Ctrl-C inside the controller's own solver, come back as its error)
            raise ControllerError(f"controller {self.name}: {what} failed at {self._where()}: {_brief(exc)}") from exc
        if timed_out:
            raise self._timed_out(what, timeout)
        # Ctrl-C that the controller, or the CasADi solve it ran, swallowed (CasADi returns it as a failed solve): the
        # evaluation ran on to the end, exit 0, its --out replaced (stop 60)
        interrupt.check()
        return out

    def _timed_out(self, what: str, timeout: float) -> ControllerError:
        return ControllerError(f"controller {self.name}: {what} did not return within the act timeout of "
                               f"{timeout:g} s (--act-timeout) at {self._where()}")


def _short(value: Any) -> str:
    return shown(value, 60)


# Limits of the settings: beyond them a run is a typo, not a plan (and a timer or an episode list past them
# fails deep inside with OverflowError: setitimer's time_t, a list of 10**20 entries).
MAX_ACT_TIMEOUT = 86400.0  # s, a day
MAX_EPISODES = 100_000


def check_act_timeout(act_timeout: float | None) -> None:
    """Raise ValueError unless ``act_timeout`` is None (off) or a number of seconds in (0, MAX_ACT_TIMEOUT]
    that can be enforced here (SIGALRM on the main thread)."""
    if act_timeout is None:
        return
    if isinstance(act_timeout, bool) or not isinstance(act_timeout, (int, float)) or not (
            0 < act_timeout <= MAX_ACT_TIMEOUT):  # (false for NaN)
        raise ValueError(f"act_timeout (--act-timeout) must be a number of seconds in (0, {MAX_ACT_TIMEOUT:g}], "
                         f"got {_short(act_timeout)}")
    if not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread():
        raise ValueError("act_timeout (--act-timeout) needs SIGALRM, i.e. a POSIX system and the main thread")


# ---------------------------------------------------------------------------------------------- evaluation
def check_target(target_time: float | None, target_ratio: float | None) -> None:
    """A clear error for a target cycle time out of range (s, in [1, 40)) or a ratio to T_min out of [1, 3]."""
    from wl_env.env import check_target_time

    if target_time is not None and target_ratio is not None:
        raise ValueError("give target_time or target_ratio, not both")
    if target_time is not None:
        check_target_time(target_time)
    if target_ratio is not None and not (isinstance(target_ratio, (int, float)) and not isinstance(target_ratio, bool)
                                         and 1.0 <= target_ratio <= 3.0):  # (false for NaN)
        raise ValueError(f"target_ratio must lie in [1, 3] (times T_min), got {_short(target_ratio)}")


def check_settings(episodes: int, init_noise: float, seed: int) -> None:
    """Raise ValueError for settings no evaluation can run with."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or not 1 <= episodes <= MAX_EPISODES:
        raise ValueError(f"episodes must be an integer in [1, {MAX_EPISODES}], got {_short(episodes)}")
    if isinstance(init_noise, bool) or not (isinstance(init_noise, (int, float)) and 0.0 <= init_noise <= 1.0):
        raise ValueError(f"init_noise must lie in [0, 1], got {_short(init_noise)}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        # (a 4300-digit seed ran the episodes, then failed to be written to the JSON)
        raise ValueError(f"seed must be an integer in [0, {MAX_SEED}], got {_short(seed)}")


def check_env_kwargs(env_id: Any, env_kwargs: Any, braking: str) -> None:
    """ValueError naming ``env_id`` unless it is a registered WheelLoader env, and ``env_kwargs`` unless it is a
    dict of its arguments that leaves the evaluation's own (``init_noise``; ``braking``, if it differs) alone:
    they were overridden without a word."""
    import gymnasium as gym

    import wl_env  # noqa: F401  (registers the envs)

    ids = sorted(k for k in gym.registry if isinstance(k, str) and k.startswith("WheelLoader"))
    if not isinstance(env_id, str) or env_id not in ids:
        raise ValueError(f"env_id must be one of {', '.join(ids)}, got {shown(env_id)}")
    if env_kwargs is None:
        return
    if not isinstance(env_kwargs, dict):
        raise ValueError(f"env_kwargs must be a dict of {env_id}'s keyword arguments, got {shown(env_kwargs)}")
    if "init_noise" in env_kwargs:
        raise ValueError("env_kwargs sets init_noise, which is the evaluation's own argument (episode 0 starts "
                         "at the nominal state): give init_noise=")
    if "scenario" in env_kwargs:  # (every episode is reset with its own scenario: the env's was dropped without a word)
        raise ValueError("env_kwargs sets scenario, which the evaluation's own arguments set (each episode is reset with "
                         "its scenario): give scenario= (one cycle) or scenarios= (a suite's list, "
                         "wl_env.suites.load_suite(name).spread(braking))")
    if "braking" in env_kwargs and env_kwargs["braking"] != braking:
        raise ValueError(f"env_kwargs braking={shown(env_kwargs['braking'])} contradicts the evaluation's braking "
                         f"{braking!r}")
    entry = gym.spec(env_id).entry_point
    cls = gym.envs.registration.load_env_creator(entry) if isinstance(entry, str) else entry
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        known = set(params) | set(inspect.signature(gym.make).parameters) - {"id", "kwargs"}  # (gym.make's own too)
        unknown = sorted(set(map(str, env_kwargs)) - known)
        if unknown:
            raise ValueError(f"env_kwargs: {env_id} takes no argument(s) {unknown}; known: {sorted(known)}")


def _takes_one(fn: Callable[..., Any]) -> bool:
    """``fn`` can be called with one positional argument (as far as its signature tells)."""
    try:
        inspect.signature(fn).bind("message")
    except TypeError:
        return False
    except ValueError:  # (a builtin without a signature: taken as it is)
        return True
    return True


def evaluate_controller(
    controller: Controller,
    braking: str | None = None,
    episodes: int = 10,
    init_noise: float = 1.0,
    seed: int = 0,
    *,
    scenario: Scenario | None = None,
    scenarios: list[Scenario] | None = None,
    score: bool = True,
    front: Any = None,
    cache: str | os.PathLike | None = None,
    trajectories: bool = False,
    env_kwargs: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
    name: str | None = None,
    act_timeout: float | None = None,
    solve: bool = True,
    env_id: str | None = None,
    unknown: str = "raise",
    target_time: float | None = None,
    target_ratio: float | None = None,
    min_time: str = "optimum",
    deferred: bool = False,
) -> dict[str, Any]:
    """Run episodes of ``controller`` and score each completed one against the optimum of its own cycle.

    Without ``scenarios``: ``episodes`` episodes of ``scenario`` (default: the nominal cycle), episode 0
    from its start, episodes 1..N-1 from starts perturbed by ``init_noise``, each scored against the
    optimum from its own start. With ``scenarios`` (a suite's list): one episode per scenario from its
    own start (``episodes`` and ``init_noise`` unused). Episode i is reset with seed ``seed + i``: the
    same call gives the same result. The optimum comes from the shipped suites' optima, the cache, or a
    direct solve (:mod:`mpc.benchmark.reference`; ``solve`` False: never solve, LookupError instead, or
    with ``unknown="skip"`` the episode left unscored);
    ``front`` (the nominal cycle's, if given) is used for the episodes it belongs to.

    The controller is told each episode's scenario if its ``reset`` takes ``scenario=``, and runs through
    :class:`GuardedController`: whatever goes wrong in its code is a :class:`ControllerError` naming it
    (``name``, default its class), the episode and the step. ``act_timeout`` (seconds, default None:
    off) fails an ``act()`` call that takes longer. ``env_id``: default the controller's ``env_id``
    attribute, else ``WheelLoader-v2``. Values that do not exist (the gaps of an unfinished cycle) are None.

    A target cycle time per episode: ``target_time`` (s), or ``target_ratio`` times the episode's own
    minimum time (its scenario and start; shipped, cached or solved as the scores are). The controller is
    told it through ``reset(target_time=...)`` (a controller without that argument is refused); each
    episode records it and its ``lateness``, (T - target) / target when positive, else 0. ``min_time``
    ``"estimate"`` takes the ratio of the scenario's estimated T_min instead (:mod:`wl_env.suites.min_time`;
    nothing solved, e.g. for training-time evaluations on unsolved draws).

    ``deferred``: the completed episodes are scored later, by :func:`score_evaluation` (e.g. in another
    process than the controller's: an optimum solved for a score then never shares a heap with torch);
    each record keeps its cycle's parameters (``params``) until then.
    """
    import gymnasium as gym

    import wl_env  # noqa: F401  (registers WheelLoader-v1/v2)
    from wl_env.rollout import run_episode

    # (switches as True or False, before any episode: solve="no" failed at the first score, after the episode had
    # run, and score="no" scored)
    score, solve, trajectories, deferred = (check_flag(n, v) for n, v in (
        ("score", score), ("solve", solve), ("trajectories", trajectories), ("deferred", deferred)))
    # (dicts, JSON text and files too, as the env takes them; anything else is a ValueError naming it)
    if scenarios is not None:
        if isinstance(scenarios, (str, bytes, dict)) or not hasattr(scenarios, "__iter__"):
            raise ValueError(f"scenarios must be a list of scenarios, got {type(scenarios).__name__}")
        scenarios = [resolve_scenario(s, braking) for s in scenarios]
    elif scenario is not None:
        scenario = resolve_scenario(scenario, braking)
    if scenarios is not None:
        if not scenarios:
            raise ValueError("scenarios is empty: nothing to evaluate")
        braking = braking or scenarios[0].braking
        episodes, init_noise = len(scenarios), 0.0
    elif scenario is not None:
        braking = braking or scenario.braking
    braking = cycle.check_braking(braking or "service")
    # (numpy scalars as the numbers they hold: np.int64(1) episodes was "must be an integer in [1, ...]")
    # (and a float32 target as the number it prints: np.float32(9.1) was recorded as itself, not JSON, 9.1000003814)
    episodes, init_noise, seed, target_time, target_ratio, act_timeout = map(
        plain, (episodes, init_noise, seed, target_time, target_ratio, act_timeout))
    check_settings(episodes, init_noise, seed)  # (before the plan: it multiplies by episodes)
    plan = list(scenarios) if scenarios is not None else [scenario or Scenario.nominal(braking)] * episodes
    for s in plan:
        if s.braking != braking:
            raise ValueError(f"scenario {s.label()} has {s.braking} braking; this evaluation runs {braking}")
    check_target(target_time, target_ratio)
    check_act_timeout(act_timeout)
    if min_time not in ("optimum", "estimate"):
        raise ValueError(f"min_time must be 'optimum' or 'estimate', got {min_time!r}")
    if unknown not in ("raise", "skip"):
        raise ValueError(f"unknown must be 'raise' or 'skip', got {shown(unknown)}")
    if progress is not None and not (callable(progress) and _takes_one(progress)):
        raise ValueError(f"progress must be a function of one message or None, got {shown(progress)}")
    if not callable(getattr(controller, "act", None)):  # (None: an AttributeError in the first step)
        raise ValueError(f"controller must have an act(obs) method (load_controller makes one from a name), got "
                         f"{type(controller).__name__}")
    if front is not None:
        from mpc.benchmark.pareto import check_front_of

        check_front_of(front, braking, None)  # (its parameters: matched per episode, see _score)
    if cache is not None:  # (checked now: a file there failed only after the episodes)
        if not isinstance(cache, (str, os.PathLike)):
            raise ValueError(f"cache must be a folder path or None, got {type(cache).__name__}")
        check_output_folder(cache, f"cache {cache}")
    chosen, env_id = env_id, env_id or getattr(controller, "env_id", "WheelLoader-v2")
    check_env_kwargs(env_id, env_kwargs, braking)
    say = progress or (lambda msg: None)
    kwargs = {**(env_kwargs or {}), "braking": braking}
    with warnings.catch_warnings():  # (the env a policy was trained on, not the user's choice: no "out of date")
        if chosen is None:
            warnings.simplefilter("ignore", DeprecationWarning)
        envs = {noise: gym.make(env_id, **{**kwargs, "init_noise": noise}) for noise in {0.0, float(init_noise)}}
    guarded = GuardedController(controller, name or type(controller).__name__, act_timeout,
                                n_actions=envs[0.0].action_space.shape[0])
    records: list[dict[str, Any]] = []
    previous_alarm = signal.signal(signal.SIGALRM, _on_alarm) if act_timeout is not None else None
    try:
        for i, sc in enumerate(plan):
            noise = 0.0 if i == 0 or scenarios is not None else float(init_noise)
            env = envs[noise]
            target = target_time
            if target_ratio is not None:  # the episode's own minimum time: its start as the reset draws it
                from mpc.benchmark.reference import min_time_of
                from wl_env.suites.min_time import estimate_min_time

                env.reset(seed=seed + i, options={"scenario": sc})
                start = env.unwrapped
                T_min = (min_time_of(braking, start.episode_params, cache, solve) if min_time == "optimum" else
                         estimate_min_time(start.episode_scenario or sc))
                target = target_ratio * T_min
            ep = run_episode(env, guarded, seed=seed + i, trajectory=trajectories, scenario=sc, target_time=target)
            if target is None and getattr(env.unwrapped, "observe_target", False):
                # a target env given none draws one (1-2.5 T_min): the controller drove to it, so the record says
                # which (it said None, and plan/bc episodes 11-16 s long read as untargeted time gaps of +50 %)
                target = float(env.unwrapped.target_time)
            ran = env.unwrapped.episode_params  # the cycle with its actual start
            ran_scenario = env.unwrapped.episode_scenario
            rec: dict[str, Any] = {"episode": i, "init_noise": noise,
                                   "scenario": None if ran_scenario is None else ran_scenario.to_dict(),
                                   # (the actual start, also where it lies outside the scenario ranges: the score's
                                   # cycle, reproducible from the file)
                                   "start_engine_speed_rad_s": float(ran.omega_0), "start_bucket_height_m": float(ran.H_0),
                                   **ep.to_dict(trajectory=trajectories),
                                   "T_min": None, "time_gap": None, "fuel_opt_g": None, "fuel_gap": None,
                                   "reference": None, "target_time": target,
                                   "lateness": (max(ep.T - target, 0.0) / target if target is not None and ep.completed
                                                else None)}
            if score and ep.completed and deferred:
                rec["params"] = ran.to_dict()
            elif score and ep.completed:
                _score(rec, braking, ran, front, cache, solve, unknown)
            records.append(rec)
            say(_episode_line(rec))
    finally:
        if act_timeout is not None:
            signal.signal(signal.SIGALRM, signal.SIG_DFL if previous_alarm is None else previous_alarm)
        for env in envs.values():
            env.close()
    return {"braking": braking, "episodes": episodes, "init_noise": float(init_noise), "seed": seed,
            "env_id": env_id, "scenario": None if scenarios is not None else plan[0].to_dict(),
            "optimum": _optimum(records),  # episode 0's (each episode records its own: T_min, fuel_opt_g)
            "summary": summarize(records), "per_episode": records}


def score_evaluation(result: dict[str, Any], front: Any = None, cache: str | os.PathLike | None = None,
                     solve: bool = True, unknown: str = "raise") -> dict[str, Any]:
    """``result`` of :func:`evaluate_controller` with ``deferred=True``, its completed episodes scored here
    (the arguments as there) and its optimum and summary updated; returned."""
    _check_keys(result, ("braking", "per_episode"), "result")
    _check_records(result["per_episode"], "result['per_episode']", RECORD_KEYS + OPTIMUM_KEYS)
    for rec in result["per_episode"]:
        params = rec.pop("params", None)
        if params is not None:
            _score(rec, result["braking"], LoaderParams.from_dict(params), front, cache, solve, unknown)
    result["optimum"], result["summary"] = _optimum(result["per_episode"]), summarize(result["per_episode"])
    return result


def _score(rec: dict[str, Any], braking: str, ran: LoaderParams, front: Any, cache: str | os.PathLike | None,
           solve: bool, unknown: str) -> None:
    """A completed episode's record scored against its own cycle's optimum (``ran``: its parameters)."""
    from mpc.benchmark.scoring import score_run

    own = front if front is not None and front.params_fingerprint == ran.fingerprint() else None
    try:
        s = score_run(rec["T"], rec["fuel_g"], braking, params=ran, front=own, cache=cache, solve=solve)
    except LookupError:
        if unknown != "skip":
            raise
    else:
        rec.update(T_min=s.T_min, time_gap=s.time_gap, fuel_opt_g=s.fuel_opt_g, fuel_gap=s.fuel_gap,
                   reference=s.reference)


# the fields of an episode's record that summarize() reads; score_evaluation() the optimum's too (evaluate_controller
# writes them all)
RECORD_KEYS = ("completed", "success", "T", "fuel_g", "max_violation", "time_gap", "fuel_gap")
OPTIMUM_KEYS = ("T_min", "fuel_opt_g", "reference")


def _check_keys(d: Any, keys: tuple[str, ...], what: str) -> None:
    """ValueError naming the keys of ``keys`` that ``d`` (``what``: an :func:`evaluate_controller` result or a part
    of one) lacks: a malformed result was a bare KeyError (or a TypeError: not a dict)."""
    if not isinstance(d, dict):
        raise ValueError(f"{what} must be a dict, as evaluate_controller returns, got {_short(d)}")
    missing = [k for k in keys if k not in d]
    if missing:
        raise ValueError(f"{what} has no {', '.join(map(repr, missing))}: not an evaluate_controller result")


def _check_records(records: Any, what: str, keys: tuple[str, ...] = RECORD_KEYS) -> None:
    """ValueError unless ``records`` is a non-empty list of episode records (with ``keys``), naming ``what``."""
    if not isinstance(records, list) or not records:
        raise ValueError(f"{what} must be a non-empty list of episode records, got {_short(records)}")
    for i, rec in enumerate(records):
        _check_keys(rec, keys, f"{what}[{i}]")


def _optimum(records: list[dict[str, Any]]) -> dict[str, Any] | None:
    first = records[0]
    return None if first["T_min"] is None else {k: first[k] for k in ("T_min", "fuel_opt_g", "reference")}


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregates over episodes: rates over all of them, times and fuels over the completed ones, the gaps
    (regret) over the successful ones (a completed cycle that missed its targets has no gap worth
    averaging; the success rate stands beside them); ``nominal`` repeats episode 0."""
    if not records:
        raise ValueError("no episodes to summarize")
    _check_records(records, "records")
    done = [r for r in records if r["completed"]]
    scored = [r for r in records if r["success"] and r["time_gap"] is not None]
    violations = [r["max_violation"] for r in records]
    nominal = records[0]
    time_gaps, fuel_gaps = [r["time_gap"] for r in scored], [r["fuel_gap"] for r in scored]
    return {
        "episodes": len(records),
        "success_rate": _mean([float(r["success"]) for r in records]),
        "completion_rate": len(done) / len(records),
        "violation_rate": _mean([float(v > 0.0) for v in violations]),  # any excess over the driver's limits
        "max_violation": max(violations),
        "mean_max_violation": _mean(violations),
        "T": _stats([r["T"] for r in done]),
        "fuel_g": _stats([r["fuel_g"] for r in done]),
        "scored": len(scored),
        "time_gap": _stats(time_gaps),
        "fuel_gap": _stats(fuel_gaps),
        "time_gap_median": _stats(time_gaps)["median"],
        "time_gap_p90": _stats(time_gaps)["p90"],
        "fuel_gap_median": _stats(fuel_gaps)["median"],
        "fuel_gap_p90": _stats(fuel_gaps)["p90"],
        # how late the completed cycles with a target finished, relative to it (0: on time; None: no targets)
        "lateness_median": _stats([r["lateness"] for r in done if r.get("lateness") is not None])["median"],
        "nominal": {k: nominal[k] for k in ("success", "completed", "T", "fuel_g", "max_violation", "time_gap",
                                            "fuel_gap")},
    }


def _mean(values: list[float]) -> float | None:
    return math.fsum(values) / len(values) if values else None


def _stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"mean": None, "std": None, "min": None, "max": None, "median": None, "p90": None}
    mean = math.fsum(values) / len(values)
    std = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / len(values))
    return {"mean": mean, "std": std, "min": min(values), "max": max(values),
            "median": float(np.median(values)), "p90": float(np.percentile(values, 90))}


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:+.2f} %"


def _episode_line(r: dict[str, Any]) -> str:
    state = "success" if r["success"] else "completed" if r["completed"] else "failed"
    return (f"  episode {r['episode']} (seed {r['seed']}, init_noise {r['init_noise']:g}): {state}, "
            f"T = {r['T']:.2f} s, fuel = {r['fuel_g']:.2f} g, time gap {_pct(r['time_gap'])}, "
            f"fuel gap {_pct(r['fuel_gap'])}, max violation {100 * r['max_violation']:.1f} %")


# the aggregate keys issue #14 names for `wl evaluate`'s JSON (its "aggregate"; the same values as in "summary")
AGGREGATE_KEYS = ("success_rate", "time_gap_median", "fuel_gap_median", "fuel_gap_p90", "lateness_median")


def aggregate(result: dict[str, Any]) -> dict[str, Any]:
    """The headline aggregates of an :func:`evaluate_controller` result (:data:`AGGREGATE_KEYS`)."""
    _check_keys(result, ("summary",), "result")
    _check_keys(result["summary"], AGGREGATE_KEYS, "result['summary']")
    return {k: result["summary"][k] for k in AGGREGATE_KEYS}


def summary_line(result: dict[str, Any], name: str) -> str:
    """One line of an :func:`evaluate_controller` result, for the command line."""
    _check_keys(result, ("braking", "summary"), "result")
    _check_keys(result["summary"], ("episodes", "success_rate", "completion_rate", "T", "fuel_g", "time_gap_median",
                                    "fuel_gap_median", "fuel_gap_p90", "scored", "max_violation"), "result['summary']")
    s = result["summary"]

    def num(stats: dict[str, float | None], fmt: str, unit: str) -> str:
        return "n/a" if stats["mean"] is None else f"{format(stats['mean'], fmt)}{unit}"

    return (f"{name}, {result['braking']} braking, {s['episodes']} episodes: success {100 * s['success_rate']:.0f} %, "
            f"completed {100 * s['completion_rate']:.0f} %, mean T {num(s['T'], '.2f', ' s')}, "
            f"mean fuel {num(s['fuel_g'], '.2f', ' g')}, median time gap {_pct(s['time_gap_median'])}, "
            f"median fuel gap {_pct(s['fuel_gap_median'])} (p90 {_pct(s['fuel_gap_p90'])}; {s['scored']} successful, scored), "
            f"max violation {100 * s['max_violation']:.1f} %")
