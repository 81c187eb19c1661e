"""Thin Typer commands: parse options, build a config, call one core function."""
