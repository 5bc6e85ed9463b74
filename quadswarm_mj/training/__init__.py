"""Training: PPO (Brax's PPO loss, networks and observation normalizer, in JAX) on the batched
CPU MuJoCo engine, with one shared policy for every quad (parameter sharing).

``quadswarm_mj.training.ppo`` imports JAX; nothing in ``quadswarm_mj`` imports it at top level.
See TRAINING.md for the commands, the measurements behind the choice of trainer and the runs.
"""
