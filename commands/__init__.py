"""Thin subcommand modules: parse options, call the engine, write via formats.

Import only click, the standard library and ``relight_cli.cli.tools`` at module
level; everything heavy is imported inside the callback.
"""
