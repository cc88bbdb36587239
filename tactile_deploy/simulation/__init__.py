"""One contact or whole datasets: indenter + pose -> FEM -> depth map, mesh, forces."""
