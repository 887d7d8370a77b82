"""File formats: one module per format (read / validate / write) and one spec (.md) each.

Formats never import torch or the engine; they exchange plain numpy arrays and
small dataclasses.  See README.md in this folder for the list.
"""
