"""``bayes-talk evaluate`` with a family's settings changed for one run (design experiments).

Two kinds of change, neither of which the command line offers:

* ``--family-defaults FAMILY=JSON``: update the family's constructor defaults
  (``bayes_talk.estimators.registry.FAMILY_DEFAULTS``), e.g.
  ``ssgpdm-phone-ctx-mean='{"private_dims": 2}'``;
* ``--learn-dynamics``: every state SGPDM learns its dynamics hyperparameters α_x, γ_x,
  β_x (with their 1/θ prior) instead of fixing them at deena2010's 100:1
  (``SGPDMConfig.learn_dynamics``; ``SwitchingModel._state_cfg`` fixes them).

Everything after ``--`` is passed to ``bayes-talk`` as it is::

    python benchmarks/analysis/family_variant.py --learn-dynamics -- evaluate --protocol deena2010 \\
        --corpus data/train250 --test-corpus data/dev40 --methods ssgpdm-phone-ctx-mean-posterior \\
        --json eval/dev_learned_dynamics.json

The evaluation must train in this process (its default, no ``--workers``): a process pool's
workers would not see the change.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bayes_talk.app.cli import main as cli_main
from bayes_talk.estimators import registry
from bayes_talk.models import switching


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        raise SystemExit("usage: family_variant.py [options] -- <bayes-talk arguments>")
    cut = argv.index("--")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family-defaults", action="append", default=[], metavar="FAMILY=JSON")
    ap.add_argument("--learn-dynamics", action="store_true")
    a = ap.parse_args(argv[:cut])
    for item in a.family_defaults:
        family, _, js = item.partition("=")
        if family not in registry.ESTIMATORS:
            raise SystemExit(f"--family-defaults: unknown family {family!r}")
        registry.FAMILY_DEFAULTS.setdefault(family, {}).update(json.loads(js))
    if a.learn_dynamics:
        fixed = switching.SwitchingModel._state_cfg

        def learned(self):
            return {**fixed(self), "learn_dynamics": True}

        switching.SwitchingModel._state_cfg = learned
    return cli_main(argv[cut + 1:])


if __name__ == "__main__":
    sys.exit(main())
