"""The hierarchical VAE: network, loss, config, training, tracing."""
