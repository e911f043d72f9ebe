"""`python -m neuralslicer.cli ...` runs the `neuralslicer` command."""
import sys

from neuralslicer.cli.main import main

sys.exit(main())
