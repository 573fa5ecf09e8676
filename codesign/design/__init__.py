"""Design of masks: figures of merit, the physical limit of the LSR/MTF trade, restorability, the LSR constraint
of co-design, the nlopt search over any family's parameter vector, and design records."""
