"""The suite's toolkit: what more than one test module needs (waits, /metrics reading, test
ports, the fake clock, the tiny scene, the one timeout setting, the deployment's generators).

Test modules never import one another (tests/unit/rules/test_test_layout.py checks it): what they
share lives here, or as a fixture in a conftest.py."""
