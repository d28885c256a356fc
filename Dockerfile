# One image for both services of docker-compose.yml (the simulator and the runtime + API).
FROM python:3.11-slim
WORKDIR /opt/testcell
COPY pyproject.toml README.md ./
COPY cell cell
COPY service service
COPY dbc dbc
RUN pip install --no-cache-dir .
ENTRYPOINT ["testcell"]
