"""The suite's environment: the `jaxfusion` commands that tests run in-process keep no compile
cache in the user's home (`lab.compile_cache`; its own tests give it a folder)."""

import os

os.environ.setdefault("JAXFUSION_COMPILE_CACHE", "off")
