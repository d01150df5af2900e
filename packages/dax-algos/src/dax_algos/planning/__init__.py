"""Planning: the planner interface and receding-horizon episode (:mod:`.planner`),
CEM-MPC (:mod:`.cem_mpc`), diff-MPC (:mod:`.diff_mpc`), diff-CEM-MPC
(:mod:`.diff_cem_mpc`), and the random and expert reference rows (:mod:`.reference`)."""
