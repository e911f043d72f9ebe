"""`python -m cli ...` runs the `neuralslicer` command."""
import sys

from cli.main import main

sys.exit(main())
