"""An instrumented package declares RORY's runtime: package.xml, setup.py, setup.cfg and
pyproject.toml edits (before/after, idempotent, formatting kept), and a whole ament_python
package instrumented, then built and installed with pip."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from rory_instrument.cli import main
from rory_instrument.packaging import (
    DISTRIBUTION,
    add_to_package_xml,
    add_to_pyproject,
    add_to_setup_cfg,
    add_to_setup_py,
)

PACKAGE_XML = '''\
<?xml version="1.0"?>
<package format="3">
  <name>talker</name>
  <version>0.1.0</version>
  <exec_depend>rclpy</exec_depend>
  <exec_depend>std_msgs</exec_depend>
  <export>
    <build_type>ament_python</build_type>
  </export>
</package>
'''


def test_package_xml_gets_an_exec_depend_after_the_others() -> None:
    new = add_to_package_xml(PACKAGE_XML)
    assert new == PACKAGE_XML.replace(
        '  <exec_depend>std_msgs</exec_depend>\n',
        f'  <exec_depend>std_msgs</exec_depend>\n  <exec_depend>{DISTRIBUTION}</exec_depend>\n')
    assert add_to_package_xml(new) is None  # idempotent


def test_package_xml_without_exec_depends_gets_one_before_export() -> None:
    text = PACKAGE_XML.replace('  <exec_depend>rclpy</exec_depend>\n', '').replace(
        '  <exec_depend>std_msgs</exec_depend>\n', '')
    new = add_to_package_xml(text)
    assert new is not None
    assert f'  <exec_depend>{DISTRIBUTION}</exec_depend>\n  <export>' in new


def test_setup_py_install_requires_grows_and_the_rest_stays() -> None:
    text = textwrap.dedent('''\
        from setuptools import setup  # ament_python

        setup(
            name='talker',
            install_requires=['setuptools'],
            entry_points={'console_scripts': ['talker = talker.node:main']},
        )
    ''')
    new, computed = add_to_setup_py(text)
    assert not computed and new is not None
    assert new == text.replace("['setuptools']", f"['setuptools', '{DISTRIBUTION}']")
    assert add_to_setup_py(new) == (None, False)


def test_setup_py_without_install_requires_gets_one() -> None:
    new, _ = add_to_setup_py("import setuptools\nsetuptools.setup(name='t')\n")
    assert new == ("import setuptools\n"
                   f"setuptools.setup(name='t', install_requires=['{DISTRIBUTION}'])\n")


def test_setup_py_with_a_computed_list_is_left_alone() -> None:
    assert add_to_setup_py("from setuptools import setup\nsetup(install_requires=REQS)\n") == (
        None, True)


def test_a_listed_requirement_with_a_version_counts_as_listed() -> None:
    text = "from setuptools import setup\nsetup(install_requires=['rory_ros2>=0.1'])\n"
    assert add_to_setup_py(text) == (None, False)


def test_setup_cfg_install_requires() -> None:
    text = '[metadata]\nname = talker\n\n[options]\ninstall_requires =\n    numpy\n\n[x]\na = 1\n'
    new = add_to_setup_cfg(text)
    assert new == text.replace('    numpy\n', f'    numpy\n    {DISTRIBUTION}\n')
    assert add_to_setup_cfg(new) is None
    bare = add_to_setup_cfg('[options]\npackages = find:\n')
    assert bare == f'[options]\ninstall_requires =\n    {DISTRIBUTION}\npackages = find:\n'
    assert add_to_setup_cfg('[metadata]\nname = t\n') is None  # no [options]: not ours to add


def test_pyproject_dependencies() -> None:
    text = ('[build-system]\nrequires = ["setuptools"]\n\n'
            '[project]\nname = "t"\ndependencies = ["numpy"]\n')
    new = add_to_pyproject(text)
    assert new == text.replace('["numpy"]', f'["{DISTRIBUTION}", "numpy"]')
    assert add_to_pyproject(new) is None
    assert add_to_pyproject('[project]\nname = "t"\n') == (
        f'[project]\ndependencies = ["{DISTRIBUTION}"]\nname = "t"\n')
    assert add_to_pyproject('[tool.poetry]\nname = "t"\n') is None


NODE = '''\
import rclpy
from rclpy.node import Node


class Talker(Node):
    def __init__(self):
        super().__init__('talker')
        self.count = 0


def main():
    rclpy.init()
    rclpy.spin(Talker())
'''

SETUP_PY = '''\
from setuptools import setup

package_name = 'talker'

setup(
    name=package_name,
    version='0.1.0',
    packages=[package_name],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    entry_points={'console_scripts': ['talker = talker.talker:main']},
)
'''


def test_an_ament_python_package_is_instrumented_and_still_installs_with_pip(
    tmp_path: Path,
) -> None:
    src = tmp_path / 'talker'
    (src / 'talker').mkdir(parents=True)
    (src / 'talker' / '__init__.py').write_text('')
    (src / 'talker' / 'talker.py').write_text(NODE)
    (src / 'resource').mkdir()
    (src / 'resource' / 'talker').write_text('')
    (src / 'package.xml').write_text(PACKAGE_XML)
    (src / 'setup.py').write_text(SETUP_PY)
    (tmp_path / 'keyvars.yaml').write_text(
        'nodes:\n  - {file: talker/talker.py, class: Talker, vars: [count]}\n')
    out = tmp_path / 'out'
    assert main([str(src), '--vars', str(tmp_path / 'keyvars.yaml'), '-o', str(out)]) == 0
    assert f'<exec_depend>{DISTRIBUTION}</exec_depend>' in (out / 'package.xml').read_text()
    assert f"install_requires=['setuptools', '{DISTRIBUTION}']" in (out / 'setup.py').read_text()
    assert (src / 'setup.py').read_text() == SETUP_PY  # SRC untouched
    # Instrumenting the output again changes nothing more.
    again = tmp_path / 'again'
    assert main([str(out), '--vars', str(tmp_path / 'keyvars.yaml'), '-o', str(again)]) == 0
    assert (again / 'setup.py').read_text() == (out / 'setup.py').read_text()
    assert (again / 'package.xml').read_text() == (out / 'package.xml').read_text()

    target = tmp_path / 'installed'
    done = subprocess.run(
        [sys.executable, '-m', 'pip', 'install', '--quiet', '--no-index', '--no-deps',
         '--no-build-isolation', '--target', str(target), str(out)],
        capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    installed = (target / 'talker' / 'talker.py').read_text()
    assert '@rory_runtime.checkpointed(vars=("count",)' in installed
    metadata = next(target.glob('talker-0.1.0.dist-info')) / 'METADATA'
    assert f'Requires-Dist: {DISTRIBUTION}' in metadata.read_text()
