# Everything else is in pyproject.toml. The cffi extension can only be
# declared here (setuptools has no pyproject key for cffi_modules).
from setuptools import setup

setup(cffi_modules=["plant/_build.py:ffibuilder"])
