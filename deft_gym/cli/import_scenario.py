"""Turn an exported OpenSCENARIO (.xosc) or CommonRoad (.xml) file back into a scenario YAML.

    deft-gym import runs/demo/flaky/reruns/0/episode.xosc            # -> .../episode.yaml
    deft-gym import runs/demo/flaky/reruns/0/episode.cr.xml --rerun  # and rerun it on its jitter seed

The ego starts as the file says, towards the destination the file's DeFT-Gym description names;
static objects stay put; every other participant becomes a scripted vehicle that replays its
recorded trajectory (two waypoints per world step, so that it has the recorded position, heading
and speed at every step). ``deft-gym run FILE.yaml --reruns 1 --jitter-seed S`` on the episode's
jitter seed reproduces the logged outcome; ``--rerun`` does that here and compares. Reads only
DeFT-Gym's own exports (their map is one of the map families): docs/interop.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

from deft_gym.cli import common
from deft_gym.files import first_line


def build_parser() -> common.Parser:
    p = common.parser("import", "deft_gym.cli.import_scenario", __doc__)
    p.add_argument("file", metavar="FILE.xosc|FILE.xml", help="an exported OpenSCENARIO or CommonRoad file")
    common.add_out(p, None, help="the scenario YAML to write (default: FILE with the suffix .yaml)", folder=False)
    p.add_argument("--rerun", action="store_true",
                   help="run the scenario once on the episode's jitter seed and compare with the logged outcome")
    p.add_argument("--reactive", action="store_true",
                   help="reactive participants come back reactive (their scenario entry, from the file's DeFT-Gym "
                        "description) instead of replaying their trajectories")
    p.add_argument("--jitter-seed", type=int, default=None, metavar="S",
                   help="the rerun's jitter seed (default: the episode's, from the file)")
    common.add_ads_config(p)
    common.add_output_flags(p)
    return p


def output_path(file: Path) -> Path:
    """``episode.xosc`` -> ``episode.yaml``, ``episode.cr.xml`` -> ``episode.cr.yaml``."""
    return file.with_suffix(".yaml")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    con = common.console(args)
    file = Path(args.file)
    if not file.is_file():
        return common.cli_error(f"FILE: {file} does not exist")
    try:
        from deft_gym.export.roundtrip import import_file

        data, meta = import_file(file, reactive=args.reactive)
    except ImportError as err:
        return common.cli_error(f"the import needs the export extra ({err.name} is missing): "
                                "pip install 'deft-gym[export]'")
    except Exception as err:  # not an export, a damaged file: one line
        return common.cli_error(f"FILE {file}: {type(err).__name__}: {err}".splitlines()[0])
    import yaml

    from deft_gym.config import ConfigError
    from deft_gym.files import write_atomic
    from deft_gym.scenarios.scenario import scenario_from_dict

    out = Path(args.out) if args.out else output_path(file)
    try:
        scenario_from_dict(data, source=str(out))  # the YAML loads as it is written
    except ConfigError as err:
        return common.cli_error(f"FILE {file}: the scenario it gives does not load: {first_line(err)}")
    seed = args.jitter_seed if args.jitter_seed is not None else meta.get("jitter_seed")
    head = (f"# imported by deft-gym import from {file}\n# {data['description']}\n"
            f"# rerun: deft-gym run {out} --reruns 1" + (f" --jitter-seed {seed}" if seed is not None else "")
            + (f" --ads-config {args.ads_config}" if args.ads_config else "") + "\n")
    write_atomic(out, head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120))
    con.print(f"{file} -> {out} ({len(data['participants'])} participants)", soft_wrap=True)
    status = 0
    if args.rerun:
        from deft_gym.bus.ads import load_ads_config
        from deft_gym.export.failures import reproduces, rerun

        try:
            ads = load_ads_config(args.ads_config)
        except ConfigError as err:
            return common.cli_error(first_line(err))
        outcome, ego = rerun(data, seed, ads)
        r = reproduces(meta, outcome, None, ego)
        logged = meta.get("outcome"), (meta.get("collision") or {}).get("participant"), (meta.get("collision") or {}).get("time")
        got = r["outcome"], r["collision"], r["collision_time"]
        con.print(f"rerun on jitter seed {seed}: {_what(*got)}; logged: {_what(*logged)} -> "
                  + ("[green]reproduced[/green]" if r["reproduced"] else "[red]differs[/red]"), soft_wrap=True)
        status = 0 if r["reproduced"] else 1
    if args.quiet:
        print(out)
    else:
        print(f"rerun: deft-gym run {out} --reruns 1" + (f" --jitter-seed {seed}" if seed is not None else ""))
    return status


def _what(outcome: str | None, who: str | None, when: float | None) -> str:
    return f"{outcome} with {who} at {float(when):.2f} s" if who else str(outcome)


if __name__ == "__main__":
    sys.exit(main())
