"""Build hook: the wheel carries the top-level ``conf/`` (the one copy of the Hydra configs) as ``torchtrack/conf``.

Everything else about the package is in pyproject.toml. A source checkout and an editable install read ``conf/`` where
it is (``torchtrack.config.CONF_DIR``); only a built wheel needs the copy inside the package.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithConf(build_py):
    def run(self):
        super().run()
        if not self.editable_mode:
            src = Path(__file__).resolve().parent / "conf"
            shutil.copytree(src, Path(self.build_lib) / "torchtrack" / "conf", dirs_exist_ok=True)


setup(cmdclass={"build_py": BuildPyWithConf})
