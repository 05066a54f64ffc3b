"""The plant as a co-simulation FMU (FMI 2.0 and 3.0): ``dct-hil fmu``.

``variables`` decides what the FMU shows (from the C structs and the
parameter files), ``model_description`` writes modelDescription.xml,
``build`` compiles the C core with the FMI layer (``csrc/``) and packs the
FMU with its sources.
"""
