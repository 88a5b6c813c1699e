"""The noise injector: ground-truth camera frames in, perturbed frames out (salt and pepper, gaussian, blur,
brightness and contrast, occlusion, JPEG, delay, drop). ``models`` is the pure, seeded core; ``service`` wires it to
the bus."""
