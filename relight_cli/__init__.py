"""relight: relighting articulated hands and 3D Gaussian avatars.

The engine is a plain Python library (no click); ``relight_cli.cli`` is the
command-line surface, ``relight_cli.commands`` the thin per-subcommand modules
and ``relight_cli.formats`` the documented file formats.
"""

__version__ = "0.1.0"
