"""Small numeric stages exercising msflow without any face code."""
