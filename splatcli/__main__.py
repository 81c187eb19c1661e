"""`python -m splatcli`: what torchrun and `train --nproc` start."""

from .cli.main import main

main()
