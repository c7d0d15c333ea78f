"""The DinerDash Gym paper's agents in JAX: behaviour cloning and DPGM (imitation), PPO and its
variants (GAIL, kick-starting), DAgger (feed-forward and sequence learners).

::

    import gymnasium, dinerdash_agents
    policy = dinerdash_agents.load("docs/results/checkpoints/dpgm-274")
    envs = gymnasium.make_vec("dinerdash:DinerDash-v0", num_envs=8)
    obs, info = envs.reset(seed=1000)
    actions, state = policy.predict(obs, None, None, action_masks=info["action_mask"])
    obs, reward, terminated, truncated, info = envs.step(actions)

The shape (Stable-Baselines3's):

- **A policy** answers ``predict(obs, state, episode_start, action_masks=...) -> (actions,
  state)`` (:class:`~dinerdash_agents.checkpoint.BasePolicy`). A feed-forward policy's state is
  ``None``; a recurrent one's (or one with memory features) carries each environment's history.
  Every rollout of the package calls this one method: DAgger's one play loop
  (:func:`dagger.play_round`) for every learner, and evaluation (through ``act``, the same
  with the state kept in the policy). :func:`load` returns one, whatever the algorithm.
- **An algorithm** is a module (``bc``, ``dpgm``, ``ppo``, ``gail``, ``kickstart``, ``dagger``,
  ``recurrent``): its config, model, loss or update, and the ``CHECKPOINT`` hooks that load it.
- **One training entry per family of algorithms**, a ``train_*`` module each: ``train_imitation``
  (from demonstrations: bc, dpgm), ``train_rl`` (PPO and its variants on the server: ppo,
  ppo-masked, gail, ppo-kickstart), ``train_dagger`` (DAgger, whatever the learner: dagger,
  dagger-recurrent). A family's members differ by a row of a table (``train_imitation.IMITATION``,
  ``train_rl.RL``, ``train_dagger.LEARNERS``), not by a second run loop.
- **One list of the algorithms a checkpoint may hold**, :data:`checkpoint.ALGORITHMS` (name ->
  module): saving writes the module, loading imports only it; checkpoints written before the
  module was recorded load through the same table.

Layout:
    errors           AgentsError and its kinds
    checkpoint       checkpoint directories, the policy shape (BasePolicy, Policy), load(), and
                     ALGORITHMS, the one table of algorithms (load imports only the one needed)
    connect          the one ConnectOptions value a run hands down; a local server if none named
    curves           the learning curve every run writes (curve.csv, curve.png) and its live
                     curves (LiveCurves: TensorBoard event files beside the checkpoint)
    seeds            the seeds a checkpoint was trained on, and evaluation seeds clear of them
    demos            reading and slicing ``python -m dinerdash collect``'s demonstrations
    supervised       the (masked) cross-entropy and the jitted minibatch loop of BC and DPGM
    bc               behaviour cloning: two FC layers with dropout between
    dpgm             DPGM: a factor graph per action, re-weighting layers, end-to-end fine-tuning
    ppo              PPO (masked or not) against batched sessions: the model, the update, and the
                     Trainer class whose four hooks its variants override
    gail             GAIL: PPO rewarded by a discriminator trained against the demonstrations
    kickstart        kick-started PPO: a BC actor, critic warm-up, a decaying pull to a teacher
    dagger           DAgger: the feed-forward learner (with or without memory), the mixture,
                     the one play loop of a round, the aggregate and its fit
    recurrent        sequence DAgger's learners (GRU, frame stack), their policy, truncated BPTT
    evaluate         playing a policy through the client's vector env (dinerdash.evaluation)
    train_imitation  a ``train bc|dpgm`` run: demonstrations -> checkpoint
    train_rl         a ``train ppo|ppo-masked|gail|ppo-kickstart`` run on the server:
                     checkpoints, curve, resume
    train_dagger     a ``train dagger|dagger-recurrent`` run: rounds, validation, curve, the
                     best round's checkpoint
    paper            the paper's experiment end to end: results.md, results.json, the bar chart
    bench            ``bench-ppo``: PPO's end-to-end env-steps/s and its profile by part
    cli              ``python -m dinerdash_agents`` (train, evaluate, paper, bench-ppo): a shell
                     over the above
"""

from __future__ import annotations

from ._version import __version__
from .checkpoint import BasePolicy, Policy, load
from .errors import AgentsError, CheckpointError, DemosError

__all__ = [
    "AgentsError",
    "BasePolicy",
    "CheckpointError",
    "DemosError",
    "Policy",
    "__version__",
    "load",
]
