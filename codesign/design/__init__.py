"""Design of masks: figures of merit, the physical limit of the LSR/MTF trade, restorability, the nlopt search over
any family's parameter vector and its re-check on a finer grid and a whole-PSF window."""
