"""SUMO files for the ring scenario: a single-lane loop network and its routes.

The ring is ``n_edges`` equal edges on a circle, joined without internal (junction)
lanes, so the distance a vehicle drives around it is exactly ``ring_length``: each
edge carries an explicit ``length`` and netconvert writes it with 6 decimals.
Routes loop with SUMO's ``repeat`` attribute, long enough for the whole episode,
so no vehicle reaches a route end mid-episode.

>>> import tempfile
>>> from mixed_traffic.envs.sumo_net import build_ring_network
>>> net = build_ring_network(313.65, tempfile.mkdtemp())
>>> net.edges, round(net.edge_length * len(net.edges), 6)
(('e0', 'e1', 'e2', 'e3'), 313.65)
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

LANE_SPEED = 100.0  # m/s; vehicles are limited by their own maxSpeed (the IDM v0)


@dataclass(frozen=True)
class RingNetwork:
    """A generated ring: the .net.xml path and the edges in driving order."""

    net_file: str
    ring_length: float
    edges: tuple[str, ...]

    @property
    def edge_length(self) -> float:
        return self.ring_length / len(self.edges)

    def edge_offsets(self) -> dict[str, float]:
        """Ring coordinate (m) at the start of every edge."""
        return {e: i * self.edge_length for i, e in enumerate(self.edges)}

    def locate(self, s: float) -> tuple[str, float]:
        """(edge, lane position) of the ring coordinate ``s`` (taken modulo the length)."""
        s = s % self.ring_length
        i = min(int(s // self.edge_length), len(self.edges) - 1)
        return self.edges[i], s - i * self.edge_length


def find_netconvert(netconvert: str | None = None) -> str:
    """Path of the netconvert binary: the given one, eclipse-sumo's, or the one on PATH."""
    if netconvert is not None:
        return netconvert
    try:
        import sumo  # the eclipse-sumo wheel

        path = os.path.join(sumo.SUMO_HOME, "bin", "netconvert")
        if os.path.exists(path):
            return path
    except ImportError:
        pass
    return shutil.which("netconvert") or "netconvert"


def build_ring_network(ring_length: float, out_dir: str, *, n_edges: int = 4,
                       netconvert: str | None = None) -> RingNetwork:
    """Write ``ring.nod.xml``/``ring.edg.xml`` into ``out_dir`` and convert them to ``ring.net.xml``.

    Raises ``ValueError`` for a bad length or edge count and ``RuntimeError`` with
    netconvert's own message when the conversion fails or the binary is missing.
    """
    if not ring_length > 0:
        raise ValueError(f"ring_length={ring_length!r} is invalid; allowed: > 0 (m)")
    if not (isinstance(n_edges, int) and n_edges >= 2):
        raise ValueError(f"n_edges={n_edges!r} is invalid; allowed: an integer >= 2")
    os.makedirs(out_dir, exist_ok=True)
    radius = ring_length / (2.0 * math.pi)
    edge_len = ring_length / n_edges

    def xy(angle: float) -> str:
        return f"{radius * math.cos(angle):.4f},{radius * math.sin(angle):.4f}"

    nodes = ["<nodes>"] + [
        f'    <node id="n{i}" x="{radius * math.cos(2 * math.pi * i / n_edges):.4f}" '
        f'y="{radius * math.sin(2 * math.pi * i / n_edges):.4f}" type="priority"/>' for i in range(n_edges)
    ] + ["</nodes>"]
    edges = ["<edges>"]
    for i in range(n_edges):
        shape = " ".join(xy(2 * math.pi * (i + m / 12) / n_edges) for m in range(13))
        edges.append(f'    <edge id="e{i}" from="n{i}" to="n{(i + 1) % n_edges}" numLanes="1" '
                     f'speed="{LANE_SPEED}" length="{edge_len:.9f}" shape="{shape}"/>')
    edges.append("</edges>")
    nod, edg = os.path.join(out_dir, "ring.nod.xml"), os.path.join(out_dir, "ring.edg.xml")
    net = os.path.join(out_dir, "ring.net.xml")
    with open(nod, "w") as f:
        f.write("\n".join(nodes) + "\n")
    with open(edg, "w") as f:
        f.write("\n".join(edges) + "\n")
    _netconvert([find_netconvert(netconvert), "-n", nod, "-e", edg, "-o", net, "--no-internal-links",
                 "--no-turnarounds", "--offset.disable-normalization", "--junctions.limit-turn-speed", "-1",
                 "--precision", "6", "--no-warnings"], net, "the ring network")
    return RingNetwork(net_file=net, ring_length=float(ring_length), edges=tuple(f"e{i}" for i in range(n_edges)))


def read_ring_network(net_file: str, ring_length: float) -> RingNetwork:
    """Check an existing network made by :func:`build_ring_network` and describe it.

    The file must be well-formed XML (SUMO 1.28 crashes on truncated files instead of
    reporting them) with edges ``e0 .. e{k-1}`` of one lane each whose lengths add up
    to ``ring_length``; otherwise a ``ValueError`` names what is wrong.
    """
    import xml.etree.ElementTree as ET

    if not os.path.exists(net_file):
        raise ValueError(f"net_file={net_file!r} is invalid; allowed: an existing .net.xml file")
    try:
        root = ET.parse(net_file).getroot()
    except ET.ParseError as e:
        raise ValueError(f"net_file={net_file!r} is not well-formed XML ({e}); allowed: a SUMO network "
                         "written by netconvert") from e
    lengths = {}
    for edge in root.iter("edge"):
        eid = edge.get("id", "")
        if eid.startswith("e") and eid[1:].isdigit() and edge.get("function") != "internal":
            lanes = edge.findall("lane")
            lengths[int(eid[1:])] = float(lanes[0].get("length", "nan")) if len(lanes) == 1 else float("nan")
    k = len(lengths)
    if k < 2 or sorted(lengths) != list(range(k)) or any(math.isnan(v) for v in lengths.values()):
        raise ValueError(f"net_file={net_file!r}: expected single-lane edges 'e0'..'e<k-1>' (k >= 2) forming the "
                         f"ring, found {sorted(lengths)}")
    total = sum(lengths.values())
    if abs(total - ring_length) > 1e-3:
        raise ValueError(f"net_file={net_file!r}: its edges add up to {total:.6f} m but ring_length={ring_length}; "
                         "allowed: a network of exactly ring_length")
    return RingNetwork(net_file=net_file, ring_length=float(ring_length), edges=tuple(f"e{i}" for i in range(k)))


@dataclass(frozen=True)
class StraightNetwork:
    """A generated straight road: one single-lane edge ``e0`` of ``length`` m (no junction on the way)."""

    net_file: str
    length: float
    edges: tuple[str, ...] = ("e0",)

    def locate(self, s: float) -> tuple[str, float]:
        """(edge, lane position) of the road coordinate ``s`` (m from the start of the road)."""
        if not 0.0 <= s <= self.length:
            raise ValueError(f"position {s:.3f} m is off the road; allowed: [0, {self.length:.3f}] m")
        return "e0", s


def build_straight_network(length: float, out_dir: str, *, netconvert: str | None = None) -> StraightNetwork:
    """Write ``road.nod.xml``/``road.edg.xml`` into ``out_dir`` and convert them to ``road.net.xml``.

    One edge, so a SUMO vehicle always sees its leader (SUMO's look-ahead only limits
    leaders on later edges). Raises ``ValueError`` for a bad length and ``RuntimeError``
    with netconvert's own message when the conversion fails or the binary is missing.
    """
    if not length > 0:
        raise ValueError(f"length={length!r} is invalid; allowed: > 0 (m)")
    os.makedirs(out_dir, exist_ok=True)
    nod, edg = os.path.join(out_dir, "road.nod.xml"), os.path.join(out_dir, "road.edg.xml")
    net = os.path.join(out_dir, "road.net.xml")
    with open(nod, "w") as f:
        f.write(f'<nodes>\n    <node id="a" x="0" y="0"/>\n    <node id="b" x="{length:.6f}" y="0"/>\n</nodes>\n')
    with open(edg, "w") as f:
        f.write(f'<edges>\n    <edge id="e0" from="a" to="b" numLanes="1" speed="{LANE_SPEED}" '
                f'length="{length:.6f}"/>\n</edges>\n')
    _netconvert([find_netconvert(netconvert), "-n", nod, "-e", edg, "-o", net, "--no-internal-links",
                 "--no-turnarounds", "--offset.disable-normalization", "--precision", "6", "--no-warnings"],
                net, "the straight road")
    return StraightNetwork(net_file=net, length=float(length))


def _netconvert(cmd: list[str], net: str, what: str) -> None:
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except FileNotFoundError as e:
        raise RuntimeError(f"netconvert: binary {cmd[0]!r} not found ({e}); install eclipse-sumo "
                           "(pip install eclipse-sumo) or pass netconvert=<path>") from e
    if res.returncode != 0 or not os.path.exists(net):
        raise RuntimeError(f"netconvert failed (exit code {res.returncode}) building {what}:\n"
                           f"{res.stderr.strip() or res.stdout.strip()}")


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle of the routes file: its vType attributes and where it starts."""

    vid: str
    vtype: dict  # SUMO vType attributes (id included)
    start: float  # ring coordinate of the front bumper (m)
    speed: float  # depart speed (m/s)


def write_routes(path: str, net: RingNetwork | StraightNetwork, vehicles: list[VehicleSpec], *,
                 laps: int | None) -> None:
    """Routes file: one vType per distinct type, every vehicle on a looping route of ``laps`` laps
    (``laps=None``: the network's edges once, e.g. the straight road)."""
    lines = ["<routes>"]
    seen = set()
    for v in vehicles:
        if v.vtype["id"] in seen:
            continue
        seen.add(v.vtype["id"])
        attrs = " ".join(f"{k}={quoteattr(str(val))}" for k, val in v.vtype.items())
        lines.append(f"    <vType {attrs}/>")
    k = len(net.edges)
    for v in vehicles:
        edge, lane_pos = net.locate(v.start)
        i0 = net.edges.index(edge)
        route = " ".join(net.edges[(i0 + j) % k] for j in range(k))
        lines.append(f'    <vehicle id="{v.vid}" type="{v.vtype["id"]}" depart="0" departPos="{lane_pos:.9f}" '
                     f'departSpeed="{v.speed:.9f}" departLane="0" insertionChecks="none">')
        repeat = "" if laps is None else f' repeat="{int(laps)}"'
        lines.append(f'        <route edges="{route}"{repeat}/>')
        lines.append("    </vehicle>")
    lines.append("</routes>")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
