"""``dopeslam config [--config FILE] [--set SECTION.KEY=VALUE]... [--out FILE]``: the resolved
configuration (defaults < file < DOPESLAM_SECTION__KEY variables < --set) as TOML, to read or to
edit and pass back with ``--config``; ``--reference`` prints every key with its default instead."""
from __future__ import annotations

from testbed.commands.options import add_config_options, config_error, config_from_args


def register(sub) -> None:
    p = sub.add_parser("config", help="print the resolved configuration (TOML), or with --reference every key")
    add_config_options(p)
    p.add_argument("--out", default=None, metavar="FILE", help="write it to FILE (.toml, else JSON) instead")
    p.add_argument("--reference", action="store_true", help="every section and key with its default (Markdown)")
    p.set_defaults(func=show)


def show(args) -> int:
    from stack.config import ConfigError, dump_toml, reference_markdown, write_config
    from testbed.settings import RunConfig

    if args.reference:
        print(reference_markdown(RunConfig))
        return 0
    try:
        config = config_from_args(args)
    except ConfigError as e:
        return config_error("config", e)
    if args.out:
        write_config(config, args.out)
        print(f"wrote {args.out}")
    else:
        print(dump_toml(config), end="")
    return 0
