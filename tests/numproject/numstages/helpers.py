"""A helper module imported by a stage: editing it must rerun that stage."""

import numpy as np


def double(x):
    return 2 * np.asarray(x)
