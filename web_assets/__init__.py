"""The dashboard's web assets (page script, header, help texts, logo): package data, found
through importlib.resources by server/assets.py in the source tree and in an installed wheel."""
