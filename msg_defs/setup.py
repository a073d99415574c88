from setuptools import find_packages, setup

package_name = "msg_defs"

# rclpy / std_msgs / diagnostic_msgs come from ROS 2 (a sourced Jazzy, or the
# pinned PyPI wheels in requirements/ros.txt), never from install_requires.
setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    python_requires=">=3.10",
    install_requires=["numpy>=1.26"],
    zip_safe=True,
    maintainer="inkdiag developers",
    maintainer_email="inkdiag@example.com",
    description="inkdiag wire contract on std_msgs.",
    license="Apache-2.0",
)
