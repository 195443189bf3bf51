"""``autocast bench NAME [--quick]`` (``python -m bench NAME``): run one bench by name."""

from __future__ import annotations

import importlib
import sys

from bench import HEADLINE_KEYS


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(f"usage: autocast bench NAME [--quick] [NAME's own flags: autocast bench NAME --help]\n"
              f"NAME: {', '.join(HEADLINE_KEYS)}; each ends with one headline line (docs/performance.md)")
        return 0
    if not argv or argv[0] not in HEADLINE_KEYS:
        print(f"autocast bench: NAME must be one of {', '.join(HEADLINE_KEYS)}", file=sys.stderr)
        return 2
    return importlib.import_module(f"bench.{argv[0]}").main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
