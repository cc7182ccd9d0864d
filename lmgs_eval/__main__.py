import sys

from lmgs_eval.cli import main

sys.exit(main())
