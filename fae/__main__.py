from fae.cli import run

run()
