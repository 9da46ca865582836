"""``LVHeartVectorEnv``: N LO hearts stepped as one jitted, vmapped-by-layout batch (DESIGN §2).

A thin stateful shell around :mod:`lvenv.env.core`: the pure ``step`` is jitted once (per static
configuration and size, shared by all instances) and serves the resets too, as a step of members
that all need a reset; a step is one device call plus one transfer of its results. Members may hold
different patients (``patient=[...]``), so one env can fit a cohort. Batches are padded to a
multiple of the device count and sharded over the CPU cores or GPUs (:mod:`lvenv.devices`).
"""

from __future__ import annotations

import collections
import functools
from typing import Any, Sequence

import gymnasium
import jax
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from lvenv import lo_model, status
from lvenv.devices import member_shardings, shard_members
from lvenv.env import core
from lvenv.env.spaces import ActionMap, observation_space
from lvenv.identification import DEFAULT_ACTION_PARAMS
from lvenv.metrics import FRAME_NAMES, OBS_NAMES
from lvenv.patients import Patient, resolve
from lvenv.plausibility import Band
from lvenv.plausibility import resolve as resolve_bands
from lvenv.simulation import DEFAULT_STEP_TOL, check_settings
from lvenv.validation import InputError, choice, integer, real, real_array

__all__ = ["LVHeartVectorEnv", "MAX_ENVS", "TRACES", "STATE_FIELDS", "info_metrics"]

#: Fields of :meth:`LVHeartVectorEnv.get_state` (host NumPy arrays, member axis first).
STATE_FIELDS = ("y", "steps", "needs_reset", "key", "parameters")

#: Traces of the jitted step per static configuration. Jitting once at module level lets
#: every env with the same configuration and size share one compiled step.
TRACES: collections.Counter = collections.Counter()


def _counted(fn):
    @functools.wraps(fn)
    def traced(*args, config):
        TRACES[config] += 1  # runs only while JAX traces
        return fn(*args, config=config)

    return traced


def _with_key(fn):
    """``fn(key, ...)`` → ``(next key, fn(subkey, ...))``: the shell's key advances inside the one call."""

    @functools.wraps(fn)
    def keyed(key, *args, config):
        key, sub = jax.random.split(key)
        return key, fn(sub, *args, config=config)

    return keyed


#: One compiled program per configuration and size: :meth:`LVHeartVectorEnv.reset` is a step of
#: members that all need a reset (`core.step` then runs `core.reset`'s simulation: each member's
#: own parameters from its cold start), so a reset compiles nothing that the steps do not use.
_step_jit = jax.jit(_counted(_with_key(core.step)), static_argnames="config")


#: Keys of a step's info that a reset's lacks.
_STEP_ONLY = ("mismatch", "clipped", "reset")


def info_metrics(info: dict[str, Any]) -> np.ndarray:
    """The observations' metrics of a step's ``info`` as one (members, n_obs) float array in
    :data:`~lvenv.metrics.OBS_NAMES` order, NaN where absent (frames the env does not record)."""
    n = len(info["status"])
    return np.stack([np.asarray(info.get(k, np.full(n, np.nan)), np.float64) for k in OBS_NAMES], axis=1)


def _traced(patient: Patient) -> bool:
    """Whether the patient targets a volume-trace frame."""
    return any(k in FRAME_NAMES for k in patient.targets)


def _scatter(old: np.ndarray, idx: np.ndarray, part: np.ndarray) -> np.ndarray:
    """``old`` (batch-last) with the members ``idx`` replaced by ``part``'s columns."""
    out = np.array(old, copy=True)
    out[..., idx] = part
    return out


#: Members of one vector env, at most: 64 times the largest batch benchmarked on a GPU (65,536),
#: and a bound that keeps a mistyped ``num_envs`` from exhausting memory before anything runs.
MAX_ENVS = 2**22


class LVHeartVectorEnv(gymnasium.vector.VectorEnv):
    """Vectorised ``lvenv/LVHeart-v0``; see :mod:`lvenv.env.core` for dynamics and reward.

    Args:
        num_envs: members N (an integer in [1, :data:`MAX_ENVS`]).
        patient: built-in name, path to a patient JSON record, :class:`~lvenv.patients.Patient`,
            record dict, or a list with one per member.
        action_params: names of the parameters under identification (default τ2, Sa, R2, R3, C, Cat).
        action_mode: ``"physical"`` (bounds of :mod:`lvenv.identification`) or ``"normalized"`` ([−1, 1]).
        max_episode_steps: truncation (``None``: never; else an integer ≥ 1).
        tolerance: terminate when the mean relative mismatch falls below it (≥ 0).
        obs_noise: relative standard deviation of Gaussian measurement noise (scalar or per
            observation, ≥ 0); drawn from the env's own key.
        steps_per_beat, max_beats, rtol, scheme, step_tol, acceleration: LO-heart integration
            (:func:`lvenv.simulate`); the env uses Anderson acceleration and, with ``scheme``
            None (default), the patients' LO heart model's scheme
            (:func:`~lvenv.env.core.default_scheme`: adaptive for the single cell, where
            ``steps_per_beat`` then only matters for ``render``; fixed for a multi-element heart).
        autoreset_mode: ``NEXT_STEP`` (default) or ``DISABLED`` (every step evaluates every
            member's action; what optimisers use).
        plausibility: the reward's physiological bands (:mod:`lvenv.plausibility`): ``True``
            (default: mean aortic pressure, and mean atrial pressure and EDP 4–25 mmHg),
            ``False`` (the aortic band only) or a sequence of ``Band``.
        volume_trace: record the volume-trace frames (``V_frame_00`` …; about 8 % of a step's
            time). ``None`` (default): when some patient targets them. Without, their
            observations are 0 and ``info`` does not hold them.

    Every argument is checked here; a bad one raises ``ValueError`` naming it, its value and
    what is allowed. ``step`` takes actions of shape exactly ``(num_envs, len(action_params))``.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(
        self,
        num_envs: int = 1,
        patient: str | Patient | dict | Sequence = "normal",
        action_params: Sequence[str] = DEFAULT_ACTION_PARAMS,
        action_mode: str = "physical",
        max_episode_steps: int | None = 200,
        tolerance: float = 1e-3,
        obs_noise: float | Sequence[float] = 0.0,
        steps_per_beat: int = 1000,
        max_beats: int = 60,
        rtol: float = 1e-4,
        scheme: str | None = None,
        step_tol: float = DEFAULT_STEP_TOL,
        acceleration: str = core.ENV_ACCELERATION,
        render_mode: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        plausibility: bool | Sequence[Band] = True,
        volume_trace: bool | None = None,
    ):
        num_envs = integer("num_envs", num_envs, 1, MAX_ENVS)
        choice("render_mode", render_mode, (None, "rgb_array"))
        try:
            autoreset_mode = AutoresetMode(autoreset_mode)
        except ValueError:
            autoreset_mode = None
        choice("autoreset_mode", autoreset_mode, (AutoresetMode.NEXT_STEP, AutoresetMode.DISABLED))
        patients = resolve(patient, num_envs)
        scheme = core.default_scheme(patients[0].heart) if scheme is None else scheme
        settings = check_settings(steps_per_beat=steps_per_beat, max_beats=max_beats, rtol=rtol, scheme=scheme, step_tol=step_tol, acceleration=acceleration)
        del settings["beats"]  # the rest are Config fields
        if max_episode_steps is not None:
            max_episode_steps = integer("max_episode_steps", max_episode_steps, 1)
        noise = real_array("obs_noise", obs_noise)
        if noise.shape not in ((), (len(OBS_NAMES),)) or np.any(~np.isfinite(noise) | (noise < 0)):
            raise InputError(f"obs_noise = {obs_noise!r} must be one finite number ≥ 0 or {len(OBS_NAMES)} of them (one per observation {OBS_NAMES})")
        noise = np.broadcast_to(noise, (len(OBS_NAMES),))
        self.metadata = {**self.metadata, "autoreset_mode": autoreset_mode}
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.patients = patients
        core.check_model(self.patients, settings["scheme"])
        if volume_trace is None:
            volume_trace = any(_traced(p) for p in self.patients)
        elif not isinstance(volume_trace, (bool, np.bool_)):
            raise InputError(f"volume_trace = {volume_trace!r} must be True, False or None (when some patient targets the frames)")
        self.config = core.Config(
            actions=ActionMap(action_params, action_mode), **settings, tolerance=real("tolerance", tolerance, 0.0),
            max_episode_steps=max_episode_steps,
            obs_noise=tuple(map(float, noise)) if np.any(noise > 0) else None,
            autoreset=autoreset_mode == AutoresetMode.NEXT_STEP,
            plausibility=resolve_bands(plausibility), volume_trace=bool(volume_trace),
        )
        self.single_action_space = self.config.actions.box()
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.single_observation_space = observation_space()
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_names = self.config.actions.names
        self.obs_names = OBS_NAMES
        self._host_params = core.env_params(self.patients)
        self._params, self._padded = shard_members(self._host_params, num_envs)
        # Where every step takes its state and key from (_step).
        self._layout = (member_shardings(self._cold_host_state(needs_reset=False), num_envs),
                        member_shardings(jax.random.PRNGKey(0), num_envs, batch_axis_of=lambda leaf: None))
        self._state: core.EnvState | None = None
        self._key: jax.Array | None = None
        self._parameters: np.ndarray | None = None  # (num_envs, k) action parameters of the last step

    @property
    def trace_count(self) -> int:
        """How often the jitted step (which also resets) was traced for this env's configuration (all instances)."""
        return TRACES[self.config]

    def _info(self, raw: dict[str, Any]) -> dict[str, Any]:
        metrics = np.asarray(raw["metrics"])[: self.num_envs]
        info: dict[str, Any] = {name: metrics[:, i] for i, name in enumerate(OBS_NAMES) if self.config.volume_trace or name not in FRAME_NAMES}
        info["status"] = status.names(np.asarray(raw["status"])[: self.num_envs])
        for key in ("converged", "beats", "steps", "mismatch", "clipped", "reset"):
            if key in raw:
                info[key] = np.asarray(raw[key])[: self.num_envs]
        info["parameters"] = dict(zip(self.action_names, np.asarray(raw["parameters"])[: self.num_envs].T))
        for key in list(info):
            if key != "parameters":
                info["_" + key] = np.ones(self.num_envs, bool)
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset every member: its patient's own parameters simulated to steady state from a cold start.

        ``options={"patient": ...}`` first replaces the patients (anything ``patient=`` takes).
        """
        if options is not None:
            if not isinstance(options, dict) or set(options) - {"patient"}:
                raise InputError(f"reset options = {options!r}: the only option is 'patient'")
            if "patient" in options:
                patients = resolve(options["patient"], self.num_envs)
                core.check_model(patients, self.config.scheme)
                self.patients = patients
                self._host_params = core.env_params(self.patients)
                self._params, _ = shard_members(self._host_params, self.num_envs)
        super().reset(seed=seed)
        if seed is None:
            seed = int(self.np_random.integers(2**31 - 1))
        fresh = self._cold_state(needs_reset=True)
        actions, _ = shard_members(np.zeros((self.num_envs, len(self.action_names))), self.num_envs, batch_axis_of=lambda leaf: 0)
        self._key = jax.random.PRNGKey(integer("seed", seed, 0, 2**63 - 1))
        state, obs, _, _, _, info = self._step(fresh, actions)
        self._state = state
        obs, info = jax.device_get((obs, {k: v for k, v in info.items() if k not in _STEP_ONLY}))
        self._parameters = np.asarray(info["parameters"])[: self.num_envs]
        return np.asarray(obs)[: self.num_envs], self._info(info)

    def _cold_host_state(self, needs_reset: bool) -> core.EnvState:
        """Every member at its patient's cold start, as host arrays (batch last, not padded)."""
        n = self.num_envs
        return core.EnvState(y=np.asarray(self._host_params.y_cold), steps=np.zeros(n, np.int32), needs_reset=np.full(n, needs_reset))

    def _cold_state(self, needs_reset: bool) -> core.EnvState:
        """Every member at its patient's cold start, padded and, for a batch spread over the devices, sharded."""
        return jax.tree.map(jax.device_put, shard_members(self._cold_host_state(needs_reset), self.num_envs)[0])

    def _step(self, state: core.EnvState, actions: jax.Array):
        """The jitted step from ``state`` (advancing the env's key). The state and key go in laid
        out the same way at every call (:func:`~lvenv.devices.member_shardings`; the key on every
        device): the step returns some of them laid out otherwise than the first call's, and a
        call whose inputs are laid out otherwise would compile the step again."""
        shardings, key_sharding = self._layout
        state, key = jax.device_put(state, shardings), jax.device_put(self._key, key_sharding)
        self._key, out = _step_jit(key, state, actions, self._params, config=self.config)
        return out

    def start_cold(self, *, seed: int = 0) -> None:
        """Put every member at its patient's cold start without simulating: the next :meth:`step`
        starts there. :meth:`reset` instead simulates every member to steady state (and compiles
        to do so), which a run that sets every member before its first step does not need:
        :func:`optim.cohort.fit_reports` fills every member with :meth:`replace_patients` first.
        ``seed`` seeds the measurement noise's key, as :meth:`reset`'s does."""
        super().reset(seed=seed)
        self._state = self._cold_state(needs_reset=False)
        self._key = jax.random.PRNGKey(integer("seed", seed, 0, 2**63 - 1))
        self._parameters = np.asarray(self.config.actions.current(self._host_params.heart))

    def _check_actions(self, actions) -> np.ndarray:
        expected = (self.num_envs, len(self.action_names))
        arr = real_array("actions", actions)
        if arr.shape != expected:
            raise InputError(f"actions has shape {arr.shape}; expected (num_envs, {len(self.action_names)}) = {expected}, one row per member with columns {self.action_names}")
        return arr

    def step(self, actions):
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        actions, _ = shard_members(self._check_actions(actions), self.num_envs, batch_axis_of=lambda leaf: 0)
        state, obs, reward, terminated, truncated, info = self._step(self._state, actions)
        self._state = state
        obs, reward, terminated, truncated, info = jax.device_get((obs, reward, terminated, truncated, info))
        n = self.num_envs
        self._parameters = np.asarray(info["parameters"])[:n]
        return np.asarray(obs)[:n], np.asarray(reward)[:n], np.asarray(terminated)[:n], np.asarray(truncated)[:n], self._info(info)

    @property
    def parameters(self) -> dict[str, np.ndarray]:
        """Each member's current value of every action parameter (physical units), by name."""
        values = self._parameters if self._parameters is not None else np.array([[float(p.heart.get(n)) for n in self.action_names] for p in self.patients])
        return {name: values[:, j].copy() for j, name in enumerate(self.action_names)}

    def get_state(self) -> dict[str, np.ndarray]:
        """The env's state as host arrays (:data:`STATE_FIELDS`): ``y`` (num_envs, 9), the LO-heart
        state each member's next step is warm-started from; ``steps`` and ``needs_reset`` (num_envs,),
        the episode bookkeeping; ``key``, the PRNG key of the measurement noise; ``parameters``
        (num_envs, k), the members' current action parameters. It is everything a resumed run needs."""
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before get_state()")
        y, steps, needs_reset, key = jax.device_get((self._state.y, self._state.steps, self._state.needs_reset, self._key))
        n = self.num_envs
        return {"y": np.asarray(y)[:, :n].T.copy(), "steps": np.asarray(steps)[:n].copy(), "needs_reset": np.asarray(needs_reset)[:n].copy(),
                "key": np.asarray(key).copy(), "parameters": self._parameters.copy()}

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore a state from :meth:`get_state` (shapes and values are checked; the env must be reset)."""
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before set_state()")
        n, k = self.num_envs, len(self.action_names)
        expected = dict(zip(STATE_FIELDS, ((n, lo_model.n_states(self._host_params.heart)), (n,), (n,), np.shape(self._key), (n, k))))
        if not isinstance(state, dict) or set(state) != set(expected):
            raise InputError(f"state must be a dict with the fields {sorted(expected)}, got {sorted(state) if isinstance(state, dict) else type(state).__name__}")
        arrays = {}
        for name, shape in expected.items():
            arr = np.asarray(state[name])
            if arr.shape != shape or arr.dtype.kind not in "iufb" or (arr.dtype.kind == "f" and not np.all(np.isfinite(arr))):
                raise InputError(f"state[{name!r}] has shape {arr.shape} and dtype {arr.dtype}; expected finite values of shape {shape}")
            arrays[name] = arr
        pad = lambda a, axis: np.concatenate([a, np.repeat(np.take(a, [-1], axis=axis), self._padded - n, axis=axis)], axis=axis)
        new = core.EnvState(y=pad(arrays["y"].T, 1), steps=pad(arrays["steps"].astype(np.int32), 0), needs_reset=pad(arrays["needs_reset"].astype(bool), 0))
        self._state = jax.tree.map(lambda value, old: jax.device_put(value.astype(old.dtype), old.sharding), new, self._state)
        self._key = jax.device_put(arrays["key"].astype(np.asarray(self._key).dtype))
        self._parameters = arrays["parameters"].astype(float)

    def replace_patients(self, members: Sequence[int], patients: Sequence) -> None:
        """Give each of ``members`` (distinct indices) a new patient, one each (anything
        ``patient=`` takes per member), without simulating: their next step starts from the new
        patient's cold start, as the first step after a reset does with ``needs_reset``. Every
        other member keeps its patient and state, so its results are unchanged bit for bit.

        This lets a long run stream many patients through a fixed number of members (one
        compiled step): :mod:`optim.cohort` refills a member as soon as its patient's fit ends.
        """
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before replace_patients()")
        idx = np.asarray(members)
        if idx.size == 0:
            return
        if idx.ndim != 1 or idx.dtype.kind not in "iu" or np.any((idx < 0) | (idx >= self.num_envs)) or len(np.unique(idx)) != len(idx):
            raise InputError(f"members = {members!r} must be distinct member indices in [0, {self.num_envs - 1}]")
        given = 1 if isinstance(patients, (str, dict, Patient)) else len(patients)
        if given != len(idx) or isinstance(patients, (str, dict, Patient)):
            raise InputError(f"replace_patients needs one patient per member: got {given} for the {len(idx)} members {idx.tolist()}")
        new = resolve(list(patients), len(idx))
        core.check_model([self.patients[0], *new], self.config.scheme)
        if not self.config.volume_trace and any(map(_traced, new)):
            raise InputError("a new patient targets the volume trace, which this env does not record; create it with volume_trace=True")
        for i, patient in zip(idx, new):
            self.patients[i] = patient
        rows = core.env_params(new)
        self._host_params = jax.tree.map(lambda old, part: _scatter(old, idx, part), self._host_params, rows)
        self._params, _ = shard_members(self._host_params, self.num_envs)
        state = self.get_state()
        state["y"][idx] = rows.y_cold.T
        state["steps"][idx] = 0
        state["needs_reset"][idx] = False
        state["parameters"][idx] = np.asarray(self.config.actions.current(rows.heart))
        self.set_state(state)

    def member_heart(self, i: int):
        """Member i's Heart at its current parameters (host-side, for plotting or re-simulation)."""
        i = integer("member index i", i, 0, self.num_envs - 1)
        return self.patients[i].heart.replace(**{k: float(v[i]) for k, v in self.parameters.items()})

    def member_state(self, i: int) -> np.ndarray:
        """Member i's LO-heart state (9,; 7 n + 4 for n elements) at the end of its last step."""
        return self.get_state()["y"][integer("member index i", i, 0, self.num_envs - 1)]

    def render(self):
        """``rgb_array``: PV loop and P/V traces of member 0 at its current parameters."""
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        from lvenv.env.render import pv_image

        return pv_image(self.member_heart(0), self.member_state(0), self.patients[0], self.config.steps_per_beat)
