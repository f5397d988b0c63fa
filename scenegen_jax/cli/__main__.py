"""`python -m scenegen_jax.cli`: the `scenegen` command."""

from scenegen_jax.cli import main

main()
