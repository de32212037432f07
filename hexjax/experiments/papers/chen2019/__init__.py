"""Chen 2019: support planning against a fixed gait on the rugged wave patch (`patch`), and the paper's
iterative incenter against the exact one (`incenter`)."""
