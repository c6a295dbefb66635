"""The simulated machine's identification runs and their identification, shared by several test modules.

Identifying the paper's nine runs takes about 6 s; four modules need the same model, so conftest.py makes it
once a session (``sim_identified``) and writes the runs' CSV files once (``sim_csv_dir``). Everything here is
deterministic (seeded scenarios), so a module gets what it would have computed itself.
"""

from __future__ import annotations

#: the paper's nine identification experiments on the simulated machining centre (the bundled model's)
SIM_EXPERIMENTS = ("spindle-1000rpm", "spindle-500rpm", "spindle-400-600rpm", "feed-x-fast", "feed-x-accel",
                   "feed-y-fast", "feed-y-accel", "feed-z-fast", "feed-z-accel")
