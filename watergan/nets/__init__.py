"""Networks: the WaterGAN generator and discriminator, and the restorer nets."""
