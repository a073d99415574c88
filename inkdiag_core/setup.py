from setuptools import find_packages, setup

package_name = "inkdiag_core"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    package_data={package_name: ["profiles/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    python_requires=">=3.10",
    install_requires=["numpy>=1.26", "scipy>=1.11", "scikit-learn>=1.6", "joblib>=1.3",
                      # PyYAML: head profiles are YAML files (inkdiag_core.head_profile)
                      "PyYAML>=6.0",
                      # numba: compiled kernels (inkdiag_core._kernels) for the labeller's screening and gate
                      # (2.4-3.1x the numpy passes they replace) and the KPI window fit (scripts/bench fdi)
                      "numba==0.68.1"],
    zip_safe=True,
    maintainer="inkdiag developers",
    maintainer_email="inkdiag@example.com",
    description="inkdiag numerical core (pure Python, no ROS).",
    license="Apache-2.0",
)
