"""Meta-World benchmark: the backward, joint and flat schedules on Meta-World tasks, seeds apart.

Each run is ``stages-train task=metaworld task.env.env_name=<task> schedule=<schedule>`` with
the task's defaults: two SAC stages (grasp, place), each with a budget of ``frames`` (500 000)
and an early stop; the flat learner gets their sum, 1 000 000 frames. The whole-task
evaluation is 100 greedy episodes of the benchmark's 500 steps from its own starts (MT1's
placements). The table and its rows (``OUT/rows.json``, ``--table-only``, ``--jobs``) are those
of ``benchmark_minigrid.py``, whose runner this is.

    python scripts/benchmark_metaworld.py --levels pick-place-v3 --schedules backward \
        --seeds 0 1 2 3 4 --out results/metaworld [OVERRIDE ...]
"""

from __future__ import annotations

from benchmark_minigrid import main

if __name__ == "__main__":
    main("metaworld", "pick-place-v3", __doc__)
