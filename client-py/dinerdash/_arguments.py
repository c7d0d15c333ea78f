"""The environments' Python arguments checked and turned into protocol messages: ``expert=``,
``config=`` and a reset's ``config`` option, arrival lists, ``render_mode=`` and reset options.
Both environments (and :func:`~dinerdash.rollout`) take them the same way from here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ._proto import pb

#: The fields of GameConfig, i.e. the keys a ``config`` mapping may hold.
CONFIG_FIELDS = tuple(f.name for f in pb.GameConfig.DESCRIPTOR.fields)

Config = Mapping[str, int] | pb.GameConfig | None


#: The ``expert=`` values that name a server-side expert, and the policy the server plays for them.
EXPERTS = {"expert": pb.POLICY_EXPERT, "planner": pb.POLICY_PLANNER}


def expert_fields(expert: bool | str) -> tuple[bool, int]:
    """CreateSession's ``expert_actions`` and ``expert_policy`` for ``expert=``: ``False`` (no
    ``expert_action``), ``True`` or ``"expert"`` (the reference heuristic), or ``"planner"`` (the
    look-ahead planner)."""
    if isinstance(expert, str):
        if expert not in EXPERTS:
            raise ValueError(f"expert must be a bool or one of {sorted(EXPERTS)}, got {expert!r}")
        return True, EXPERTS[expert]
    return bool(expert), pb.POLICY_EXPERT


def make_config(config: Config) -> pb.GameConfig | None:
    """A GameConfig from a mapping such as ``{"lives": 3, "time_limit": 1000}``."""
    if config is None or isinstance(config, pb.GameConfig):
        return config
    if not isinstance(config, Mapping):
        raise TypeError(
            f"config: expected a mapping of {CONFIG_FIELDS}, got {type(config).__name__}"
        )
    unknown = sorted(set(config) - set(CONFIG_FIELDS))
    if unknown:
        raise ValueError(
            f"config: unknown field(s) {unknown}; the fields are {list(CONFIG_FIELDS)}"
        )
    msg = pb.GameConfig()
    for key, value in config.items():
        if value is not None:
            if int(value) < 0:
                raise ValueError(f"config: {key} must be a non-negative integer, got {value!r}")
            setattr(msg, key, int(value))
    return msg


def _arrival(group: Any) -> pb.Arrival:
    if isinstance(group, Mapping):
        return pb.Arrival(customer_type=int(group["customer_type"]), size=int(group["size"]))
    customer_type, size = group
    return pb.Arrival(customer_type=int(customer_type), size=int(size))


def make_arrivals(arrivals: Any, num_envs: int = 1) -> list[pb.ArrivalList]:
    """ArrivalLists from one list of ``(customer_type, size)`` pairs (every environment gets it)
    or, for a vector env, a list of such lists (one per environment)."""
    if arrivals is None:
        return []
    first = arrivals[0] if len(arrivals) else {}  # one list: its first a pair or a mapping
    if isinstance(first, Mapping) or (len(first) == 2 and all(np.ndim(x) == 0 for x in first)):
        return [pb.ArrivalList(groups=[_arrival(g) for g in arrivals])]
    lists = [pb.ArrivalList(groups=[_arrival(g) for g in one]) for one in arrivals]
    if num_envs == 1 and len(lists) != 1:
        raise ValueError("arrivals: give one list of (customer_type, size) pairs")
    return lists


RENDER_MODES = ("ansi", "rgb_array")


def check_render_mode(render_mode: str | None) -> str | None:
    """``render_mode`` if it is one of :data:`RENDER_MODES` or ``None``; else ValueError."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(
            f"render_mode must be None or one of {list(RENDER_MODES)}, got {render_mode!r}"
        )
    return render_mode


def check_options(options: Mapping[str, Any] | None, known: Sequence[str]) -> dict[str, Any]:
    """The reset ``options`` as a dict, refusing keys outside ``known``."""
    options = dict(options or {})
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(
            f"reset options: unknown key(s) {unknown}; known: {', '.join(map(repr, known))}"
        )
    return options
