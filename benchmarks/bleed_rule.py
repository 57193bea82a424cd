"""`crfedit eval edits` with a recolour's bleed refit on or off (supervised.BLEED_LIMIT).

    python benchmarks/bleed_rule.py off|LIMIT eval edits MODEL DATA --strategies hybrid --json --seed 0

``off`` never refits (the rule before 2026-11-28); a number sets the share of held points that
may bleed before a recolour is fitted again with the bottleneck layer (the default, 0.01).
Everything after it is the crfedit command line.
"""

from __future__ import annotations

import sys

import crfedit.edit.supervised as supervised
from crfedit.cli import main

if __name__ == "__main__":
    limit = sys.argv.pop(1) if len(sys.argv) > 1 else "--help"
    try:
        supervised.BLEED_LIMIT = 2.0 if limit == "off" else float(limit)  # a share above 1: never
    except ValueError:
        print(__doc__.strip(), file=sys.stderr if limit not in ("-h", "--help") else sys.stdout)
        sys.exit(0 if limit in ("-h", "--help") else 2)
    sys.exit(main())
