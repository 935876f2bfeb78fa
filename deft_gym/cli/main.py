"""``deft-gym``: one command for every program (``deft-gym <command> --help``).

Each command is a module's ``main(argv)``; the module is imported only when its command runs,
so ``deft-gym --help`` imports nothing heavy. The modules keep working as ``python -m MODULE``.
"""

from __future__ import annotations

import importlib
import sys

from deft_gym.cli import common

# command -> (module, one line); grouped as the help lists them. The modules are named, not
# imported: each loads only when its command runs (agents, deft_gym.experiments and
# deft_gym.robustness.stress hold their own packages' commands).
COMMANDS: dict[str, tuple[str, str]] = {
    # simulate
    "run": ("deft_gym.cli.run", "run a scenario N times on the jittered ADS; logs, table, pictures"),
    "calibrate": ("deft_gym.cli.calibrate", "how many collision scenarios are flaky over reruns"),
    "generate": ("deft_gym.cli.generate", "generated scenarios as YAML, optionally run once each"),
    "bench": ("deft_gym.cli.bench", "simulation speed and recording overhead"),
    "digest": ("deft_gym.cli.digest", "behaviour digests that prove a change neutral"),
    # look at episodes
    "render": ("deft_gym.cli.render", "plot and video of episodes (LOG, episode.json or a folder)"),
    "report": ("deft_gym.cli.report", "one HTML page for a run folder: numbers, plots, failures"),
    # failures in standard formats
    "export": ("deft_gym.cli.export", "failures as OpenSCENARIO + OpenDRIVE and CommonRoad XML, checked"),
    "import": ("deft_gym.cli.import_scenario", "an exported .xosc / CommonRoad .xml back to a scenario YAML"),
    # DeFT: logs -> planning-module tests
    "extract": ("deft_gym.cli.extract", "deterministic planning-module tests (pytest) from episode logs"),
    "check-planner": ("extract.contract", "check a planner's contract on a log's frames"),
    "verify": ("extract.verify", "a log's integrity (chunk CRCs, counts)"),
    # the adversary
    "train": ("agents.train", "train the RL adversary (stable-baselines3)"),
    "evaluate": ("agents.evaluate", "compare adversaries at an equal budget of scenarios"),
    "eval-report": ("agents.eval_report", "re-render an evaluation's tables and plots"),
    "findings": ("agents.findings", "re-simulate and draw a sample of each root cause an evaluation counted"),
    "bench-env": ("deft_gym.cli.bench_env", "adversary env steps/s and scenarios/hour; --profile: where its CPU goes"),
    "standing": ("deft_gym.cli.standing", "how long mutated runs stand with no light holding them (the stuck time)"),
    # robustness (ASTAA)
    "stress": ("deft_gym.robustness.stress", "robustness campaign: exceptional values on the live bus"),
    # experiments and tools
    "demo": ("deft_gym.cli.demo", "the end-to-end demo (make demo): flaky -> deterministic, adversary, report"),
    "record": ("deft_gym.experiments.record", "record one episode (optionally renamed topics, headers)"),
    "extract-eval": ("deft_gym.experiments.extract_eval", "DeFT's research questions on a scenario pool"),
    "planner-edits": ("deft_gym.experiments.planner_edits", "do generated tests catch small planner edits?"),
    "log-damage": ("deft_gym.experiments.log_damage", "damage logs on purpose and check what the reader recovers"),
    "bench-scale": ("deft_gym.cli.bench_scale", "a campaign at 1..N workers, local processes and Ray"),
}
GROUPS = (("simulate", ("run", "calibrate", "generate", "bench", "digest")),
          ("look at episodes", ("render", "report")),
          ("failures in standard formats", ("export", "import")),
          ("DeFT: logs -> planning-module tests", ("extract", "check-planner", "verify")),
          ("the adversary", ("train", "evaluate", "eval-report", "findings", "bench-env", "standing")),
          ("robustness (ASTAA)", ("stress",)),
          ("experiments and tools", ("demo", "record", "extract-eval", "planner-edits", "log-damage", "bench-scale")))


def usage() -> str:
    """The top-level help text."""
    lines = ["usage: deft-gym [--version] <command> [options]   (deft-gym <command> --help)", "",
             "DeFT-Gym: test autonomous-driving planners - jittered ADS simulation, RL adversary,",
             "deterministic planning-module tests from logs (DeFT), robustness testing (ASTAA).", ""]
    for title, names in GROUPS:
        lines.append(f"{title}:")
        lines += [f"  {n:<15} {COMMANDS[n][1]}" for n in names]
        lines.append("")
    lines.append("shared options (every command that has them): --scenarios, --out (default under runs/), "
                 "--workers (default: the CPUs), --seed, --jitter-seed, --no-progress, --quiet, --render")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    if args[0] == "--version":
        print(f"deft-gym {common.version()}")
        return 0
    name = args[0]
    if name not in COMMANDS:
        close = [c for c in COMMANDS if c.startswith(name[:3])]
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        return common.cli_error(f"unknown command {name!r}{hint} (deft-gym --help lists them)")
    common.INVOKED_AS = "deft-gym"
    try:
        module = importlib.import_module(COMMANDS[name][0])
        return int(module.main(args[1:]) or 0)
    except KeyboardInterrupt:  # the user's Ctrl-C: one line, never a traceback
        print(f"deft-gym {name}: interrupted; what is on disk stays (run the same command again to resume "
              "where it resumes)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
