"""The Gymnasium environment over the real stack (``env``), its reward (``reward``), its place on the bus
(``link``), the stacks it runs on (``stack``) and its keyword arguments (``options``)."""
