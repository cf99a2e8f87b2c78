"""bench/berlin_twice.py: the ~2000-junction stand-in of real OSM topology is built deterministically."""

import sumolib
from scriptload import load_script

bt = load_script("bench/berlin_twice.py")


def test_two_copies_joined_at_the_seam_byte_identical(tmp_path):
    one, two = tmp_path / "a.net.xml", tmp_path / "b.net.xml"
    bt.build(one)
    bt.build(two)
    assert one.read_bytes() == two.read_bytes()
    berlin, net = sumolib.net.readNet(str(bt.BERLIN)), sumolib.net.readNet(str(one))
    assert len(net.getNodes()) == 2 * len(berlin.getNodes()) == 2066
    assert len(net.getTrafficLights()) == 2 * len(berlin.getTrafficLights())
    seam = [e for e in net.getEdges() if e.getID().startswith("seam")]
    assert len(seam) == 12 and all(e.allows("passenger") for e in seam)
    # each seam link joins the west copy to the east one (ids prefixed b_), both ways
    ends = {(e.getFromNode().getID().startswith("b_"), e.getToNode().getID().startswith("b_")) for e in seam}
    assert ends == {(False, True), (True, False)}
