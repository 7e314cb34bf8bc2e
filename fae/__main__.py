import sys

from fae.cli import main

sys.exit(main())
