import os
from glob import glob

from setuptools import find_packages, setup

package_name = "hybrid_kinematics_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=[package_name, f"{package_name}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml"]),
        (f"share/{package_name}/config", [f for f in glob("config/*") if os.path.isfile(f)]),
        (f"share/{package_name}/config/import", glob("config/import/*.yaml")),
        (f"share/{package_name}/config/ur_kinematics", glob("config/ur_kinematics/*")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="hybrid_kinematics_ros maintainers",
    maintainer_email="maintainers@hybrid-kinematics.dev",
    description="Hybrid (analytic + residual network) kinematics for serial robots.",
    license="Apache-2.0",
    extras_require={"test": ["pytest", "hypothesis"]},
    entry_points={
        "console_scripts": [
            "hybrid-kinematics = hybrid_kinematics_ros.cli.main:main",
            "kinematics_node = hybrid_kinematics_ros.nodes.kinematics_node:main",
            "sim_cell_node = hybrid_kinematics_ros.nodes.sim_cell_node:main",
            "recorder_node = hybrid_kinematics_ros.nodes.recorder_node:main",
        ],
    },
)
