"""Regenerates the headline tables and figures: every result the README and the schedules'
figures show.

Each table file in ``docs/tables/`` starts with the commands that wrote it; this script runs
them again, in order, into ``--out/<table>`` (the launches of one table share it: their rows
make one table) and writes the table back to ``docs/tables/<table>.md``; the MiniGrid tables'
runs are drawn as ``docs/minigrid_schedules.png``, and the schedules' tables draw
``docs/schedules_<task>.png`` themselves (``--figures ../docs``). That is hours on a 2-core
CPU (MiniGrid most of it); ``--only`` picks tables.

``--quick`` runs each benchmark script once, on the first launch of its first table, with
``experiment=smoke``'s budgets, one seed and its first variant: minutes, so that the whole
pipeline is tested. Its tables stay in ``--out`` (the docs' copies are left alone).

    python scripts/regenerate.py --list
    python scripts/regenerate.py --out runs/regenerated                 # the full runs
    python scripts/regenerate.py --quick --out /tmp/quick
    python scripts/regenerate.py --only gridworld_seeds_0_9 --out runs/regenerated
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TABLES = ROOT / "docs" / "tables"

#: the README's results, each row's tables
HEADLINES = (
    "gridworld_seeds_0_9",
    "gridworld_seeds_10_19",
    "manipulator_ddpg_seeds_0_7",
    "manipulator_ddpg_seeds_8_17",
    "cargo_sdql_and_single_robots",
    "minigrid_keycorridor_s3r2_settings",
    "minigrid_keycorridor_s3r3_settings",
    "minigrid_keycorridor_s3r3_settings_flat",
    "minigrid_doorkey16_eval256",
    "minigrid_doorkey16_eval256_joint",
    "minigrid_doorkey16_eval256_flat",
    "minigrid_unlockpickup_advantage",
    "waypoints_gym_env",
    "seeds_wallclock_four_ways",
)
#: the schedules' figures (success against frames, per task family) and their tables
SCHEDULES = ("schedules_gridworld", "schedules_manipulator", "schedules_cargo")


#: the README's figure: every MiniGrid headline table's runs (scripts/figure_minigrid.py)
FIGURE = ROOT / "docs" / "minigrid_schedules.png"
MINIGRID_FIGURE = tuple(name for name in HEADLINES if name.startswith("minigrid_"))


def launches(table: Path) -> list[list[str]]:
    """The commands at the top of ``table``, each as ``[script, args...]`` (its ``--out``,
    ``--table`` and ``--figures`` left out: this script sets them)."""
    text = table.read_text()
    header = text.split("```text\n", 1)[1].split("\n```", 1)[0] if "```text\n" in text else ""
    found = []
    for line in header.splitlines():
        if not line.startswith("$ "):
            continue
        words = shlex.split(line[2:])
        start = words.index("python") + 1
        script, args = Path(words[start]).name, words[start + 1 :]
        kept: list[str] = []
        skip = False
        for word in args:
            if skip:
                skip = False
            elif word in ("--out", "--table", "--figures"):
                skip = True
            else:
                kept.append(word)
        found.append([script, *kept])
    if not found:
        raise SystemExit(f"error: {table} names no command (a line '$ python ...' on its top)")
    return found


def quick(argv: list[str]) -> list[str]:
    """``argv`` on the shortest budgets: one seed (two for the many-seeds timing, in the two
    ways that need no extra), the first variant, one repeat, one job, ``experiment=smoke``
    after any preset of its own."""
    script, args = argv[0], argv[1:]
    if script == "benchmark_seeds.py":  # the two ways that need no extra (joblib's: [sweep])
        args = [a for a in args if a != "--memory"] + ["--ways", "vectorized", "sequential"]
    keep = {"--seeds": 2 if script == "benchmark_seeds.py" else 1, "--variants": 1}
    overrides, options = [w for w in args if "=" in w and not w.startswith("-")], []
    for word in (w for w in args if w not in overrides):
        if word.startswith("--"):
            options.append([word])
        else:  # a value of the option before it
            options[-1].append(word)
    out = []
    for option, *values in options:
        if option == "--repeats":
            values = ["1"]
        if option != "--jobs":
            out += [option, *values[: keep.get(option, len(values))]]
    presets = [w for w in overrides if w.startswith("experiment=")]
    if presets:
        overrides[overrides.index(presets[0])] = presets[0].replace("=", "=[", 1) + ",smoke]"
    else:
        overrides.append("experiment=smoke")
    return [script, *overrides, *out]  # first: an option of several values ends there


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/regenerated"))
    every = [*HEADLINES, *SCHEDULES]
    parser.add_argument("--only", nargs="+", choices=every, default=every)
    parser.add_argument("--quick", action="store_true", help="tiny budgets, tables in --out")
    parser.add_argument("--list", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args()
    planned: list[tuple[str, list[str]]] = []
    scripts_seen: set[str] = set()
    for name in args.only:
        for argv in launches(TABLES / f"{name}.md"):
            if args.quick:
                if argv[0] in scripts_seen:
                    break
                scripts_seen.add(argv[0])
                argv = quick(argv)
            planned.append((name, argv))
    for name, argv in planned:
        out = args.out.resolve() / name  # shown as runs/<name> in the table (portable paths)
        command = [sys.executable, *argv, "--out", str(out)]
        if not args.quick:  # the docs' copies, from scripts/ as it is run
            command += ["--table", f"../docs/tables/{name}.md"]
            command += ["--figures", "../docs"] if name in SCHEDULES else []
        print(f"{name}: {shlex.join(command[1:])}", flush=True)
        if args.list:
            continue
        run(name, command)
    minigrid = [n for n in dict.fromkeys(n for n, _ in planned) if n in MINIGRID_FIGURE]
    if minigrid:  # the figure of the MiniGrid tables (in --quick: the quick ones, in --out)
        tables = [TABLES / f"{n}.md" for n in MINIGRID_FIGURE]
        figure = FIGURE
        if args.quick:
            tables = [args.out.resolve() / n / "table.md" for n in minigrid]
            figure = args.out.resolve() / FIGURE.name
        draw = [sys.executable, "figure_minigrid.py", "--out", str(figure), *map(str, tables)]
        print(f"{FIGURE.name}: {shlex.join(draw[1:])}", flush=True)
        if not args.list:
            run(FIGURE.name, draw)


def run(name: str, command: list[str]) -> None:
    """Runs ``command`` from ``scripts/``; a failure ends the regeneration, naming it."""
    done = subprocess.run(command, cwd=ROOT / "scripts")
    if done.returncode != 0:
        raise SystemExit(f"error: {name}: exit {done.returncode}: {shlex.join(command[1:])}")


if __name__ == "__main__":
    main()
