#!/usr/bin/env python
"""`python tools/convert.py ...` = `stg-convert ...`: compress, import, export and merge models.

The logic lives in stg_train.convert; see `python tools/convert.py --help`.
"""
import sys

from stg_train.cli.convert import main

if __name__ == "__main__":
    sys.exit(main())
