"""`metegs-synth`: write a rainy / foggy copy of a dataset from a real met record (or explicit numbers).

    metegs-synth --output out/synthetic-storm                        # built-in scene, shipped storm
    metegs-synth --data SCENE --depth-from RUN --record PRSA.csv --time 2016-07-20T02:30Z --output out/x
    metegs-synth --precip-mm-h 20 --visibility-m 300 --kinds rain+fog --output out/y

The output holds a degraded copy of the dataset in its own format (the synthetic scene becomes a
nerfstudio dataset with its exact depth), the clean images in sibling ``*_clean/`` folders (parsers
expose them as clean references), ``weather.json`` (θ per view, the record, kinds, seed, scale) and
``preview.png`` (clean vs degraded for a few views). It is written atomically and reproducible from
``--seed``.
"""

from __future__ import annotations

import tyro

from metegs.cli import run_cli


def entrypoint() -> None:
    """Console script `metegs-synth`."""
    from metegs.synth.pipeline import SynthConfig, synthesise

    run_cli(lambda: synthesise(tyro.cli(SynthConfig, prog="metegs-synth")))


if __name__ == "__main__":
    entrypoint()
