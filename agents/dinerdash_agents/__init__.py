"""The DinerDash Gym paper's agents in JAX: behaviour cloning and DPGM (imitation), PPO and GAIL.

::

    import gymnasium, dinerdash_agents
    policy = dinerdash_agents.load("docs/results/checkpoints/dpgm-274")
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=8)
    obs, info = envs.reset(seed=1000)
    obs, reward, terminated, truncated, info = envs.step(policy.act(obs, info["action_mask"]))

Layout:
    demos            reading and slicing ``python -m dinerdash collect``'s demonstrations
    supervised       the (masked) cross-entropy and the jitted minibatch loop of BC and DPGM
    bc               behaviour cloning: two FC layers with dropout between
    dpgm             DPGM: a factor graph per action, re-weighting layers, end-to-end fine-tuning
    ppo              PPO (masked or not) against batched sessions: the model and the Trainer
    gail             GAIL: PPO rewarded by a discriminator trained against the demonstrations
    kickstart        kick-started PPO: a BC actor, critic warm-up, a decaying pull to a teacher
    checkpoint       saving and loading checkpoint directories; the Policy that load() returns
    train_imitation  one ``train bc|dpgm`` run: demonstrations -> checkpoint
    train_rl         one ``train ppo|ppo-masked|gail|ppo-kickstart`` run on the server:
                     checkpoints, curve, resume
    evaluate         playing a policy through the client's vector env (dinerdash.evaluation)
    paper            the paper's experiment end to end: results.md, results.json, the bar chart
    bench            ``bench-ppo``: PPO's end-to-end env-steps/s and its profile by part
    cli              ``python -m dinerdash_agents`` (train, evaluate, paper, bench-ppo): a shell
                     over the above
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from .checkpoint import Policy, load
from .errors import AgentsError, CheckpointError, DemosError

try:
    __version__ = version("dinerdash-agents")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0"

__all__ = ["AgentsError", "CheckpointError", "DemosError", "Policy", "load"]
