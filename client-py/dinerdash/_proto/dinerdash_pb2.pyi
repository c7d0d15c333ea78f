from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class AutoresetMode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    AUTORESET_MODE_UNSPECIFIED: _ClassVar[AutoresetMode]
    AUTORESET_MODE_NEXT_STEP: _ClassVar[AutoresetMode]
    AUTORESET_MODE_SAME_STEP: _ClassVar[AutoresetMode]
    AUTORESET_MODE_DISABLED: _ClassVar[AutoresetMode]

class Policy(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    POLICY_UNSPECIFIED: _ClassVar[Policy]
    POLICY_EXPERT: _ClassVar[Policy]
    POLICY_RANDOM: _ClassVar[Policy]
    POLICY_PLANNER: _ClassVar[Policy]
AUTORESET_MODE_UNSPECIFIED: AutoresetMode
AUTORESET_MODE_NEXT_STEP: AutoresetMode
AUTORESET_MODE_SAME_STEP: AutoresetMode
AUTORESET_MODE_DISABLED: AutoresetMode
POLICY_UNSPECIFIED: Policy
POLICY_EXPERT: Policy
POLICY_RANDOM: Policy
POLICY_PLANNER: Policy

class GameConfig(_message.Message):
    __slots__ = ("arrival_interval", "patience_type1", "patience_type2", "decay_type1", "decay_type2", "reading_ticks", "cooking_ticks", "eating_ticks", "lives", "time_limit")
    ARRIVAL_INTERVAL_FIELD_NUMBER: _ClassVar[int]
    PATIENCE_TYPE1_FIELD_NUMBER: _ClassVar[int]
    PATIENCE_TYPE2_FIELD_NUMBER: _ClassVar[int]
    DECAY_TYPE1_FIELD_NUMBER: _ClassVar[int]
    DECAY_TYPE2_FIELD_NUMBER: _ClassVar[int]
    READING_TICKS_FIELD_NUMBER: _ClassVar[int]
    COOKING_TICKS_FIELD_NUMBER: _ClassVar[int]
    EATING_TICKS_FIELD_NUMBER: _ClassVar[int]
    LIVES_FIELD_NUMBER: _ClassVar[int]
    TIME_LIMIT_FIELD_NUMBER: _ClassVar[int]
    arrival_interval: int
    patience_type1: int
    patience_type2: int
    decay_type1: int
    decay_type2: int
    reading_ticks: int
    cooking_ticks: int
    eating_ticks: int
    lives: int
    time_limit: int
    def __init__(self, arrival_interval: _Optional[int] = ..., patience_type1: _Optional[int] = ..., patience_type2: _Optional[int] = ..., decay_type1: _Optional[int] = ..., decay_type2: _Optional[int] = ..., reading_ticks: _Optional[int] = ..., cooking_ticks: _Optional[int] = ..., eating_ticks: _Optional[int] = ..., lives: _Optional[int] = ..., time_limit: _Optional[int] = ...) -> None: ...

class CreateSessionRequest(_message.Message):
    __slots__ = ("num_envs", "config", "seed", "autoreset_mode", "action_masks", "expert_actions", "expert_policy")
    NUM_ENVS_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    AUTORESET_MODE_FIELD_NUMBER: _ClassVar[int]
    ACTION_MASKS_FIELD_NUMBER: _ClassVar[int]
    EXPERT_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    EXPERT_POLICY_FIELD_NUMBER: _ClassVar[int]
    num_envs: int
    config: GameConfig
    seed: int
    autoreset_mode: AutoresetMode
    action_masks: bool
    expert_actions: bool
    expert_policy: Policy
    def __init__(self, num_envs: _Optional[int] = ..., config: _Optional[_Union[GameConfig, _Mapping]] = ..., seed: _Optional[int] = ..., autoreset_mode: _Optional[_Union[AutoresetMode, str]] = ..., action_masks: _Optional[bool] = ..., expert_actions: _Optional[bool] = ..., expert_policy: _Optional[_Union[Policy, str]] = ...) -> None: ...

class CreateSessionResponse(_message.Message):
    __slots__ = ("session_id", "spec", "shm_doorbell", "shm_secret", "shm_server_pid")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SPEC_FIELD_NUMBER: _ClassVar[int]
    SHM_DOORBELL_FIELD_NUMBER: _ClassVar[int]
    SHM_SECRET_FIELD_NUMBER: _ClassVar[int]
    SHM_SERVER_PID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    spec: Spec
    shm_doorbell: str
    shm_secret: bytes
    shm_server_pid: int
    def __init__(self, session_id: _Optional[str] = ..., spec: _Optional[_Union[Spec, _Mapping]] = ..., shm_doorbell: _Optional[str] = ..., shm_secret: _Optional[bytes] = ..., shm_server_pid: _Optional[int] = ...) -> None: ...

class Spec(_message.Message):
    __slots__ = ("num_envs", "observation_size", "observation_low", "observation_high", "observation_dtype", "num_actions", "ruleset", "server_version", "autoreset_mode", "config", "action_masks", "expert_actions", "expert_policy")
    NUM_ENVS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_SIZE_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_LOW_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_HIGH_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_DTYPE_FIELD_NUMBER: _ClassVar[int]
    NUM_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    RULESET_FIELD_NUMBER: _ClassVar[int]
    SERVER_VERSION_FIELD_NUMBER: _ClassVar[int]
    AUTORESET_MODE_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    ACTION_MASKS_FIELD_NUMBER: _ClassVar[int]
    EXPERT_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    EXPERT_POLICY_FIELD_NUMBER: _ClassVar[int]
    num_envs: int
    observation_size: int
    observation_low: _containers.RepeatedScalarFieldContainer[int]
    observation_high: _containers.RepeatedScalarFieldContainer[int]
    observation_dtype: str
    num_actions: int
    ruleset: str
    server_version: str
    autoreset_mode: AutoresetMode
    config: GameConfig
    action_masks: bool
    expert_actions: bool
    expert_policy: Policy
    def __init__(self, num_envs: _Optional[int] = ..., observation_size: _Optional[int] = ..., observation_low: _Optional[_Iterable[int]] = ..., observation_high: _Optional[_Iterable[int]] = ..., observation_dtype: _Optional[str] = ..., num_actions: _Optional[int] = ..., ruleset: _Optional[str] = ..., server_version: _Optional[str] = ..., autoreset_mode: _Optional[_Union[AutoresetMode, str]] = ..., config: _Optional[_Union[GameConfig, _Mapping]] = ..., action_masks: _Optional[bool] = ..., expert_actions: _Optional[bool] = ..., expert_policy: _Optional[_Union[Policy, str]] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class Arrival(_message.Message):
    __slots__ = ("customer_type", "size")
    CUSTOMER_TYPE_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    customer_type: int
    size: int
    def __init__(self, customer_type: _Optional[int] = ..., size: _Optional[int] = ...) -> None: ...

class ArrivalList(_message.Message):
    __slots__ = ("groups",)
    GROUPS_FIELD_NUMBER: _ClassVar[int]
    groups: _containers.RepeatedCompositeFieldContainer[Arrival]
    def __init__(self, groups: _Optional[_Iterable[_Union[Arrival, _Mapping]]] = ...) -> None: ...

class ResetRequest(_message.Message):
    __slots__ = ("session_id", "seed", "seeds", "arrivals", "config", "reset_mask")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    SEEDS_FIELD_NUMBER: _ClassVar[int]
    ARRIVALS_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    RESET_MASK_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    seed: int
    seeds: _containers.RepeatedScalarFieldContainer[int]
    arrivals: _containers.RepeatedCompositeFieldContainer[ArrivalList]
    config: GameConfig
    reset_mask: bytes
    def __init__(self, session_id: _Optional[str] = ..., seed: _Optional[int] = ..., seeds: _Optional[_Iterable[int]] = ..., arrivals: _Optional[_Iterable[_Union[ArrivalList, _Mapping]]] = ..., config: _Optional[_Union[GameConfig, _Mapping]] = ..., reset_mask: _Optional[bytes] = ...) -> None: ...

class StepRequest(_message.Message):
    __slots__ = ("session_id", "actions")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    actions: bytes
    def __init__(self, session_id: _Optional[str] = ..., actions: _Optional[bytes] = ...) -> None: ...

class Batch(_message.Message):
    __slots__ = ("num_envs", "observations", "rewards", "terminated", "truncated", "scores", "lost", "ticks", "action_masks", "expert_actions", "reset", "seeds", "final_observations", "final_scores", "final_lost", "final_ticks", "stream_episodes", "final_action_masks", "final_expert_actions", "drain_remaining_ms")
    NUM_ENVS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    REWARDS_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    SCORES_FIELD_NUMBER: _ClassVar[int]
    LOST_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    ACTION_MASKS_FIELD_NUMBER: _ClassVar[int]
    EXPERT_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    RESET_FIELD_NUMBER: _ClassVar[int]
    SEEDS_FIELD_NUMBER: _ClassVar[int]
    FINAL_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    FINAL_SCORES_FIELD_NUMBER: _ClassVar[int]
    FINAL_LOST_FIELD_NUMBER: _ClassVar[int]
    FINAL_TICKS_FIELD_NUMBER: _ClassVar[int]
    STREAM_EPISODES_FIELD_NUMBER: _ClassVar[int]
    FINAL_ACTION_MASKS_FIELD_NUMBER: _ClassVar[int]
    FINAL_EXPERT_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    DRAIN_REMAINING_MS_FIELD_NUMBER: _ClassVar[int]
    num_envs: int
    observations: bytes
    rewards: bytes
    terminated: bytes
    truncated: bytes
    scores: bytes
    lost: bytes
    ticks: bytes
    action_masks: bytes
    expert_actions: bytes
    reset: bytes
    seeds: _containers.RepeatedScalarFieldContainer[int]
    final_observations: bytes
    final_scores: bytes
    final_lost: bytes
    final_ticks: bytes
    stream_episodes: _containers.RepeatedScalarFieldContainer[int]
    final_action_masks: bytes
    final_expert_actions: bytes
    drain_remaining_ms: int
    def __init__(self, num_envs: _Optional[int] = ..., observations: _Optional[bytes] = ..., rewards: _Optional[bytes] = ..., terminated: _Optional[bytes] = ..., truncated: _Optional[bytes] = ..., scores: _Optional[bytes] = ..., lost: _Optional[bytes] = ..., ticks: _Optional[bytes] = ..., action_masks: _Optional[bytes] = ..., expert_actions: _Optional[bytes] = ..., reset: _Optional[bytes] = ..., seeds: _Optional[_Iterable[int]] = ..., final_observations: _Optional[bytes] = ..., final_scores: _Optional[bytes] = ..., final_lost: _Optional[bytes] = ..., final_ticks: _Optional[bytes] = ..., stream_episodes: _Optional[_Iterable[int]] = ..., final_action_masks: _Optional[bytes] = ..., final_expert_actions: _Optional[bytes] = ..., drain_remaining_ms: _Optional[int] = ...) -> None: ...

class ForkRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class SnapshotRequest(_message.Message):
    __slots__ = ("session_id", "env_start", "env_count")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ENV_START_FIELD_NUMBER: _ClassVar[int]
    ENV_COUNT_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    env_start: int
    env_count: int
    def __init__(self, session_id: _Optional[str] = ..., env_start: _Optional[int] = ..., env_count: _Optional[int] = ...) -> None: ...

class SnapshotResponse(_message.Message):
    __slots__ = ("snapshot",)
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    snapshot: bytes
    def __init__(self, snapshot: _Optional[bytes] = ...) -> None: ...

class RestoreRequest(_message.Message):
    __slots__ = ("snapshot",)
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    snapshot: bytes
    def __init__(self, snapshot: _Optional[bytes] = ...) -> None: ...

class RenderRequest(_message.Message):
    __slots__ = ("session_id", "env_index", "color")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ENV_INDEX_FIELD_NUMBER: _ClassVar[int]
    COLOR_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    env_index: int
    color: bool
    def __init__(self, session_id: _Optional[str] = ..., env_index: _Optional[int] = ..., color: _Optional[bool] = ...) -> None: ...

class RenderResponse(_message.Message):
    __slots__ = ("text",)
    TEXT_FIELD_NUMBER: _ClassVar[int]
    text: str
    def __init__(self, text: _Optional[str] = ...) -> None: ...

class RolloutRequest(_message.Message):
    __slots__ = ("policy", "seeds", "config", "max_steps", "action_masks")
    POLICY_FIELD_NUMBER: _ClassVar[int]
    SEEDS_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    MAX_STEPS_FIELD_NUMBER: _ClassVar[int]
    ACTION_MASKS_FIELD_NUMBER: _ClassVar[int]
    policy: Policy
    seeds: _containers.RepeatedScalarFieldContainer[int]
    config: GameConfig
    max_steps: int
    action_masks: bool
    def __init__(self, policy: _Optional[_Union[Policy, str]] = ..., seeds: _Optional[_Iterable[int]] = ..., config: _Optional[_Union[GameConfig, _Mapping]] = ..., max_steps: _Optional[int] = ..., action_masks: _Optional[bool] = ...) -> None: ...

class Episode(_message.Message):
    __slots__ = ("seed", "steps", "observations", "actions", "rewards", "expert_actions", "action_masks", "score", "lost", "terminated", "truncated")
    SEED_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    REWARDS_FIELD_NUMBER: _ClassVar[int]
    EXPERT_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    ACTION_MASKS_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    LOST_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    seed: int
    steps: int
    observations: bytes
    actions: bytes
    rewards: bytes
    expert_actions: bytes
    action_masks: bytes
    score: int
    lost: int
    terminated: bool
    truncated: bool
    def __init__(self, seed: _Optional[int] = ..., steps: _Optional[int] = ..., observations: _Optional[bytes] = ..., actions: _Optional[bytes] = ..., rewards: _Optional[bytes] = ..., expert_actions: _Optional[bytes] = ..., action_masks: _Optional[bytes] = ..., score: _Optional[int] = ..., lost: _Optional[int] = ..., terminated: _Optional[bool] = ..., truncated: _Optional[bool] = ...) -> None: ...

class ServerInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ServerInfoResponse(_message.Message):
    __slots__ = ("server_version", "ruleset", "max_sessions", "max_envs_per_session", "session_ttl_seconds", "live_sessions", "max_rollout_episodes", "max_message_bytes", "snapshot_version", "max_memory_bytes", "memory_used_bytes", "max_rollout_work_steps", "http_port", "http_host")
    SERVER_VERSION_FIELD_NUMBER: _ClassVar[int]
    RULESET_FIELD_NUMBER: _ClassVar[int]
    MAX_SESSIONS_FIELD_NUMBER: _ClassVar[int]
    MAX_ENVS_PER_SESSION_FIELD_NUMBER: _ClassVar[int]
    SESSION_TTL_SECONDS_FIELD_NUMBER: _ClassVar[int]
    LIVE_SESSIONS_FIELD_NUMBER: _ClassVar[int]
    MAX_ROLLOUT_EPISODES_FIELD_NUMBER: _ClassVar[int]
    MAX_MESSAGE_BYTES_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_VERSION_FIELD_NUMBER: _ClassVar[int]
    MAX_MEMORY_BYTES_FIELD_NUMBER: _ClassVar[int]
    MEMORY_USED_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_ROLLOUT_WORK_STEPS_FIELD_NUMBER: _ClassVar[int]
    HTTP_PORT_FIELD_NUMBER: _ClassVar[int]
    HTTP_HOST_FIELD_NUMBER: _ClassVar[int]
    server_version: str
    ruleset: str
    max_sessions: int
    max_envs_per_session: int
    session_ttl_seconds: int
    live_sessions: int
    max_rollout_episodes: int
    max_message_bytes: int
    snapshot_version: int
    max_memory_bytes: int
    memory_used_bytes: int
    max_rollout_work_steps: int
    http_port: int
    http_host: str
    def __init__(self, server_version: _Optional[str] = ..., ruleset: _Optional[str] = ..., max_sessions: _Optional[int] = ..., max_envs_per_session: _Optional[int] = ..., session_ttl_seconds: _Optional[int] = ..., live_sessions: _Optional[int] = ..., max_rollout_episodes: _Optional[int] = ..., max_message_bytes: _Optional[int] = ..., snapshot_version: _Optional[int] = ..., max_memory_bytes: _Optional[int] = ..., memory_used_bytes: _Optional[int] = ..., max_rollout_work_steps: _Optional[int] = ..., http_port: _Optional[int] = ..., http_host: _Optional[str] = ...) -> None: ...
