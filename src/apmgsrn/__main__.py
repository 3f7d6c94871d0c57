import sys

from apmgsrn.cli.main import main

sys.exit(main())
