"""Engine entry points, one per job: loaded inputs and options in, arrays out.

A job takes what a command has already read (hands, env maps, models, cameras) and
returns or yields arrays plus the settings its provenance records: no paths to read, no
click, no printing.  Commands are thin wrappers over them (options → usage checks →
inputs → job → writers), and Python users, benchmarks and studies call them directly.
"""
