"""A measured run of the real robot and the fit of its physics (``snakeloco fit-robot``)."""
