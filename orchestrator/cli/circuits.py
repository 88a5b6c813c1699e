"""``drivebench circuits list|show|import``: the circuit library from the command line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from circuits import CircuitError, circuit_names, load_circuit
from orchestrator.cli.errors import EXIT_OK, UsageError


def add(commands: argparse._SubParsersAction) -> None:
    circuits = commands.add_parser("circuits", help="list, show and import circuits")
    circuit_commands = circuits.add_subparsers(dest="circuits_command", required=True)
    listing = circuit_commands.add_parser("list", help="every circuit: name, lap length, road width, source")
    listing.add_argument("--json", action="store_true", help="one JSON array on stdout instead of the table")
    show = circuit_commands.add_parser("show", help="a top-down picture of a circuit (start point and direction)")
    show.add_argument("name", help="circuit name (also random:SEED, twisty:SEED, grandprix:SEED)")
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


GENERATED = (
    ("random:SEED", "400-1500", "3.0", "generated from the seed: a spline, gentle bends"),
    ("twisty:SEED", "400-1500", "3.0", "generated from the seed: straights and 8.5-12 m hairpins"),
    (
        "grandprix:SEED",
        "600-1500",
        "3.0",
        "generated from the seed: a Grand Prix layout: 120-300 m straights, an 8.25-9.75 m hairpin, a chicane",
    ),
)


def _list(*, as_json: bool) -> None:
    """Every circuit; a user's circuit that cannot load is listed with the reason, never hides the others."""
    found: list[dict[str, object]] = []
    for name in circuit_names():
        try:
            circuit = load_circuit(name)
        except CircuitError as error:
            found.append({"name": name, "length_m": None, "road_width_m": None, "source": f"cannot load: {error}"})
            continue
        width_m = round(2 * circuit.road_half_width_m, 3)
        found.append(
            {"name": name, "length_m": round(circuit.length_m, 1), "road_width_m": width_m, "source": circuit.source}
        )
    if as_json:
        generated = [{"name": row[0], "length_m": None, "road_width_m": 3.0, "source": row[3]} for row in GENERATED]
        print(json.dumps(found + generated, indent=2))
        return
    rows = [("name", "lap (m)", "road (m)", "source")]
    for item in found:
        length = "-" if item["length_m"] is None else f"{item['length_m']:.1f}"
        width = "-" if item["road_width_m"] is None else f"{item['road_width_m']:.1f}"
        rows.append((str(item["name"]), length, width, str(item["source"])))
    rows += GENERATED
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    for row in rows:
        print(f"{row[0]:<{widths[0]}}  {row[1]:>{widths[1]}}  {row[2]:>{widths[2]}}  {row[3]}")


def command_circuits(args: argparse.Namespace) -> int:
    try:
        if args.circuits_command == "list":
            _list(as_json=args.json)
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
