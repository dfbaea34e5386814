import sys

from cmcan.cli import main

sys.exit(main())
