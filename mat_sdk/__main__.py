from mat_sdk.cli import main

main()
