"""stg-web: the browser player's static files (plain ES modules, no build step) and `export_web`.

The JavaScript and HTML here are package data; `stg-convert export-web` copies them beside a model.
docs/web.md describes the player, its API and how to embed it.
"""
