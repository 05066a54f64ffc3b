# Everything else is in pyproject.toml. The cffi extensions can only be
# declared here (setuptools has no pyproject key for cffi_modules).
from setuptools import setup

setup(cffi_modules=["plant/_build.py:ffibuilder", "can_dbc/_build.py:ffibuilder",
                     "rt_loop/_build.py:ffibuilder", "tcu_stub/_build.py:ffibuilder"])
