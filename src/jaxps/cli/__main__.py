import sys

from ._main import console

sys.exit(console())
