"""How a gait fares: consistency against the physics' spread, robustness over variations."""
