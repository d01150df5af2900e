"""Reinforcement learning: PPO (:mod:`.ppo`), APG (:mod:`.apg`) and SHAC (:mod:`.shac`);
their objectives as pure functions (:mod:`.losses`), the Gaussian policy's maths
(:mod:`.gaussian`) and what their training loops share (:mod:`.training`)."""
