"""Reinforcement learning: PPO (:mod:`.ppo`), APG (:mod:`.apg`) and SHAC (:mod:`.shac`)."""
