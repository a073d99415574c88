from glob import glob

from setuptools import find_packages, setup

package_name = "inkdiag_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob(package_name + "/config/*.yaml")
         + glob(package_name + "/config/*.xml")),
    ],
    package_data={package_name: ["config/*.yaml", "config/*.xml"]},
    python_requires=">=3.10",
    # rclpy and the message packages come from ROS 2 (sourced Jazzy or the
    # PyPI wheels of requirements/ros.txt), never from install_requires.
    # threadpoolctl: every node process limits its BLAS threads (inkdiag_ros.blas);
    # threadpool_limits(limits=, user_api="blas") as used there is in 3.x.
    # tqdm: `inkdiag train`'s progress bar on stderr (a plain one without it).
    # rosbags: rosbag2 bags (MCAP) for inkdiag record / replay and the offline verbs
    # (inkdiag_ros.bags); pure Python, no rclpy. Writer(version=8|9, storage_plugin=MCAP) and
    # add_connection(offered_qos_profiles=[Qos]) as used there are in 0.10 (0.11.9 tested).
    # mcap (Foxglove's MCAP library, which rosbag2's own MCAP storage follows): a bag rosbags cannot open (an MCAP
    # file without its summary: a recorder killed, a copy cut short; no metadata.yaml) is read record by record from
    # each file's start (inkdiag_ros.bags.SalvageReader: StreamReader(emit_chunks=True), breakup_chunk) rather than
    # lost whole; 1.6.0 tested.
    install_requires=["numpy>=1.26", "threadpoolctl>=3.1", "tqdm>=4.66", "rosbags>=0.10", "mcap>=1.1"],
    zip_safe=True,
    maintainer="inkdiag developers",
    maintainer_email="inkdiag@example.com",
    description="inkdiag rclpy nodes.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            # the nodes through _launch: a stop while they import exits 0, as once they run
            "loopback = inkdiag_ros._launch:loopback",
            "printhead_sim = inkdiag_ros._launch:printhead_sim",
            "fdi = inkdiag_ros._launch:fdi",
            "fe = inkdiag_ros._launch:fe",
            "record_baseline = inkdiag_ros._launch:record_baseline",
            "graph = inkdiag_ros._launch:graph",
            "inkdiag_echo = inkdiag_ros._launch:echo",  # not `echo`: it would shadow coreutils echo on the PATH
            "inkdiag = inkdiag_ros.cli:main",
        ],
    },
)
