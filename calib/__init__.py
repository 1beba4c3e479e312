"""Calibration numerics: kinematics, error models, identification, identifiability, compensation.

Pure numpy/scipy: no file I/O, no CLI. Units inside: mm and radians unless a name says otherwise
(``*_deg``). Interfaces to files and users are in degrees and converted at the edge.
"""
