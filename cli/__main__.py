"""`python -m neuralslicer.cli ...` runs the `neuralslicer` command."""
import sys

from neuralslicer.cli.main import main

if __name__ == "__main__":   # not when a process spawned by the command imports its main module
    sys.exit(main())
