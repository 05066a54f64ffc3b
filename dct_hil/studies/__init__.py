"""Studies over the offline closed loop: parameter sweeps and parameter fits.

- ``dct_hil.studies.sweep``: ``dct-hil sweep SPEC.toml``: a grid, random or Latin
  hypercube sample over plant parameters, TCU calibration values and
  maneuvers or scenarios, evaluated on Dask; results as Parquet and CSV,
  resumable, plots (``dct_hil.studies.plots``).
- ``dct_hil.studies.fit``: ``dct-hil fit MEASUREMENT --params ...``: plant parameters
  identified from a recorded run by least squares, candidates evaluated on the
  same Dask engine (``dct_hil.studies.engine``).
- ``dct_hil.studies.runs``: one run (a case, parameter overrides, calibration) and its
  figures; what the Dask workers execute.
- ``dct_hil.studies.keys``: dotted parameter keys (``vehicle.mass_kg``,
  ``clutch[0].mu_static``) and TCU calibration keys (``tcu.UPSHIFT_RPM[4]``).

Every user error is a ``StudyError``: one line naming the file, key or
channel. Nothing here imports ``dct_hil``.
"""


class StudyError(ValueError):
    """A spec, key, measurement or cluster that cannot be used (one line)."""
