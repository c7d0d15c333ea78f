"""The DinerDash Gym paper's agents in JAX: behaviour cloning and DPGM (imitation), PPO and GAIL.

::

    import gymnasium, dinerdash_agents
    policy = dinerdash_agents.load("docs/results/checkpoints/dpgm-274")
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=8)
    obs, info = envs.reset(seed=1000)
    obs, reward, terminated, truncated, info = envs.step(policy.act(obs, info["action_mask"]))

Layout (each algorithm module holds the algorithm, each ``train_*`` module one run of it):
    errors           AgentsError and its kinds
    checkpoint       checkpoint directories, the Policy that load() returns, and the registry
                     the algorithm modules add themselves to (load imports only the one needed)
    connect          the one ConnectOptions value a run hands down; a local server if none named
    curves           the learning curve every run writes (curve.csv, curve.png)
    demos            reading and slicing ``python -m dinerdash collect``'s demonstrations
    supervised       the (masked) cross-entropy and the jitted minibatch loop of BC and DPGM
    bc               behaviour cloning: two FC layers with dropout between
    dpgm             DPGM: a factor graph per action, re-weighting layers, end-to-end fine-tuning
    ppo              PPO (masked or not) against batched sessions: the model and the Trainer
    gail             GAIL: PPO rewarded by a discriminator trained against the demonstrations
    kickstart        kick-started PPO: a BC actor, critic warm-up, a decaying pull to a teacher
    dagger           DAgger: the learner (with or without memory), the mixture policy, a round
    evaluate         playing a policy through the client's vector env (dinerdash.evaluation)
    train_imitation  one ``train bc|dpgm`` run: demonstrations -> checkpoint
    train_rl         one ``train ppo|ppo-masked|gail|ppo-kickstart`` run on the server:
                     checkpoints, curve, resume
    train_dagger     one ``train dagger`` run: rounds, validation, curve, the best round's
                     checkpoint
    paper            the paper's experiment end to end: results.md, results.json, the bar chart
    bench            ``bench-ppo``: PPO's end-to-end env-steps/s and its profile by part
    cli              ``python -m dinerdash_agents`` (train, evaluate, paper, bench-ppo): a shell
                     over the above
"""

from __future__ import annotations

from ._version import __version__
from .checkpoint import Policy, load
from .errors import AgentsError, CheckpointError, DemosError

__all__ = ["AgentsError", "CheckpointError", "DemosError", "Policy", "__version__", "load"]
