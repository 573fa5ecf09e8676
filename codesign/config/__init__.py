"""Configuration plumbing: OmegaConf resolvers (run directories under torchrun) and the runtime settings every
experiment shares (debug shrinking, device, threads, precision, seed, logging)."""
