fn main() {
    eprintln!("the gateway demo is not built yet");
}
