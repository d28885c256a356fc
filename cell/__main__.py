import sys

from cell.app.cli import main

sys.exit(main())
