"""What is fitted after the VAE: the slider density, the member path head, the physics head."""
