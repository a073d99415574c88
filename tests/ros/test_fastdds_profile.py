"""The Fast DDS profile the scripts and tests run with."""


def test_fastdds_profile_only_adds_a_large_shared_memory_segment():
    """The shipped Fast DDS profile: valid XML, one SHM transport of >= 8 MB, nothing that
    could reach past this machine (no UDP/TCP transport, no peers, no locators)."""
    import importlib.resources
    import os
    import xml.etree.ElementTree as ET

    path = importlib.resources.files("inkdiag_ros") / "config" / "fastdds_profile.xml"
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_profile.xml")
    root = ET.parse(str(path)).getroot()
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    transports = root.findall(".//p:transport_descriptor", ns)
    assert [t.find("p:type", ns).text for t in transports] == ["SHM"]
    assert int(transports[0].find("p:segment_size", ns).text) >= 8 * 2**20
    text = path.read_text()
    for word in ("UDPv4", "TCPv4", "initialPeersList", "Locator", "address"):
        assert word not in text
