"""``drivebench circuits list|show|import``: the circuit library from the command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from circuits import CircuitError, circuit_names, load_circuit
from orchestrator.cli.errors import EXIT_OK, UsageError


def add(commands: argparse._SubParsersAction) -> None:
    circuits = commands.add_parser("circuits", help="list, show and import circuits")
    circuit_commands = circuits.add_subparsers(dest="circuits_command", required=True)
    circuit_commands.add_parser("list", help="every circuit: name, lap length, road width, source")
    show = circuit_commands.add_parser("show", help="a top-down picture of a circuit (start point and direction)")
    show.add_argument("name", help="circuit name (also random:SEED, twisty:SEED)")
    show.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    show.add_argument("--width", type=int, default=800, help="picture width in pixels (default 800)")
    importer = circuit_commands.add_parser(
        "import", help="import a racetrack-database centreline CSV (x_m,y_m,w_tr_right_m,w_tr_left_m)"
    )
    importer.add_argument("file", type=Path, help="the CSV file")
    importer.add_argument("--name", required=True, help="name to use it by (letters, digits, _ . -)")
    importer.add_argument("--scale", type=float, default=1.0, help="scale factor (default 1: real size)")
    importer.add_argument("--overwrite", action="store_true", help="replace an imported circuit of that name")
    circuits.set_defaults(func=command_circuits)


def command_circuits(args: argparse.Namespace) -> int:
    try:
        if args.circuits_command == "list":
            rows = [("name", "lap (m)", "road (m)", "source")]
            for name in circuit_names():
                try:
                    circuit = load_circuit(name)
                except CircuitError as error:  # one broken user file must not hide the others
                    rows.append((name, "-", "-", f"cannot load: {error}"))
                    continue
                rows.append((name, f"{circuit.length_m:.1f}", f"{2 * circuit.road_half_width_m:.1f}", circuit.source))
            rows.append(("random:SEED", "400-1500", "3.0", "generated from the seed: a spline, gentle bends"))
            rows.append(("twisty:SEED", "400-1500", "3.0", "generated from the seed: straights and 8.5-12 m hairpins"))
            widths = [max(len(row[i]) for row in rows) for i in range(3)]
            for row in rows:
                print(f"{row[0]:<{widths[0]}}  {row[1]:>{widths[1]}}  {row[2]:>{widths[2]}}  {row[3]}")
        elif args.circuits_command == "show":
            from circuits.picture import save_circuit_picture

            circuit = load_circuit(args.name)
            save_circuit_picture(circuit, args.output, width_px=args.width)
            print(f"{circuit.name}: {circuit.length_m:.1f} m -> {args.output}", file=sys.stderr)
        elif args.circuits_command == "import":
            from circuits.importer import import_racetrack_csv

            path = import_racetrack_csv(args.file, name=args.name, scale=args.scale, overwrite=args.overwrite)
            circuit = load_circuit(args.name)
            print(
                f"imported {args.name}: {circuit.length_m:.1f} m, road {2 * circuit.road_half_width_m:.1f} m -> {path}",
                file=sys.stderr,
            )
    except CircuitError as error:
        raise UsageError(str(error)) from None
    return EXIT_OK
