import sys

from psdcal.cli import main

sys.exit(main())
