"""The design steps, for any converter spec: PI tuning, data collection, identification, the classical designs, the
explicit NNPC's distillation, the frequency response, sweeps -- and the controllers they make, by name. The studies
(:mod:`cosim.study`: the paper's reproduction, a converter's study) are built on them; nothing here imports a study.
"""
