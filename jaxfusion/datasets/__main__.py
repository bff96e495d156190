"""`python -m jaxfusion.datasets`: the same commands as `jaxfusion list | render | save | bench`.

An entry point, not a library module: it hands over to the application's `jaxfusion.lab.data`.
"""

import sys

from jaxfusion.lab import data

if __name__ == "__main__":
  sys.exit(data.run())
