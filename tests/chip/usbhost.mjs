export class UsbHost {
  constructor(board) {
    this.board = board;
  }
  take() {
    return { reports: [] };
  }
}
