"""Studies: the simulated convergence study and the real/synthetic scene studies (see ``autoalign.experiments``)."""
