"""Adapting the template to a person: fitting, correspondences, anatomy transfer.

PAPER_METHODS: the feature-point fits of papers 000-002 (fae.adapt.multilevel), named
here so that the command line can offer them without importing the fitting code.
"""

PAPER_METHODS = ("multilevel", "rbf", "wendland", "multiquadric")
